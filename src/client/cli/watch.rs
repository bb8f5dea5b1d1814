//! `cellgate watch`: everything the cell publishes, as lines.

use clap::Args;

use super::{ClientCommand, ConnectArgs, Io};
use crate::client::render::{self, WatchPrinter};
use crate::client::{Client, ClientError, WatchEvent};
use cellgate_core::pb;

/// `cellgate watch`.
#[derive(Debug, Clone, Args)]
pub struct WatchArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Only this machine's events, or this PLC's (its stations, transfers and tags).
    #[arg(value_name = "MACHINE")]
    pub machine: Option<String>,
    /// PLC tag changes to print as well: `--tags` every tag, `--tags=parts,recipe` those.
    /// Without it tag changes are left out (a counter tag changes every second and would
    /// drown everything else), unless MACHINE is a PLC.
    #[arg(
        long,
        value_name = "NAMES",
        num_args = 0..=1,
        require_equals = true,
        default_missing_value = "*",
        value_delimiter = ','
    )]
    pub tags: Option<Vec<String>>,
    /// One JSON object per line.
    #[arg(long)]
    pub json: bool,
    /// Stop after this many lines (default: until Ctrl-C).
    #[arg(long, value_name = "N")]
    pub count: Option<u64>,
}

impl WatchArgs {
    /// Whether a tag change is printed.
    fn shows_tag(&self, tag: &pb::TagValue, plc_watched: bool) -> bool {
        plc_watched
            || self
                .tags
                .as_ref()
                .is_some_and(|names| names.iter().any(|n| n == "*" || *n == tag.name))
    }
}

impl ClientCommand for WatchArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        // A name that is neither a machine nor a PLC of the cell would print nothing, ever.
        let mut plc_watched = false;
        if let Some(m) = &self.machine {
            match client.status(Some(m)).await {
                Ok(_) => {}
                Err(e) if e.refusal() == Some(pb::ErrorCode::UnknownMachine) => {
                    let plcs: Vec<String> = client
                        .plc_status(None)
                        .await
                        .unwrap_or_default()
                        .into_iter()
                        .map(|p| p.plc)
                        .collect();
                    if !plcs.contains(m) {
                        let machines: Vec<String> = client
                            .status(None)
                            .await
                            .unwrap_or_default()
                            .into_iter()
                            .map(|s| s.machine)
                            .collect();
                        return Err(ClientError::InvalidArgument {
                            what: format!("watch {m}"),
                            reason: format!(
                                "cell {} has no machine or PLC {m:?}; its machines: {}; its \
                                 PLCs: {}",
                                client.cell(),
                                list_or_none(&machines),
                                list_or_none(&plcs)
                            ),
                        });
                    }
                    plc_watched = true;
                }
                Err(e) => return Err(e),
            }
        }
        let mut watch = client.watch().await?;
        let mut printer = WatchPrinter::new();
        let mut printed = 0;
        let interrupt = tokio::signal::ctrl_c();
        tokio::pin!(interrupt);
        while self.count.is_none_or(|n| printed < n) {
            let event = tokio::select! {
                e = watch.next() => e,
                _ = &mut interrupt => break,
            };
            let Some(event) = event else {
                watch.close().await;
                return Err(ClientError::Closed {
                    what: "watch".to_string(),
                });
            };
            if let Some(m) = &self.machine
                && render::watch_machine(&event) != Some(m.as_str())
            {
                continue;
            }
            if let WatchEvent::Tag(t) = &event
                && !self.shows_tag(t, plc_watched)
            {
                continue;
            }
            let now = cellgate_core::pb::now_ms();
            let line = if self.json {
                Some(render::watch_json(&event, now).to_string())
            } else {
                printer.line(&event, now)
            };
            if let Some(line) = line {
                // A closed stdout (`cellgate watch | head`) ends the watch.
                if writeln!(io.out, "{line}")
                    .and_then(|()| io.out.flush())
                    .is_err()
                {
                    break;
                }
                printed += 1;
            }
        }
        watch.close().await;
        Ok(0)
    }
}

fn list_or_none(names: &[String]) -> String {
    if names.is_empty() {
        "none".to_string()
    } else {
        names.join(", ")
    }
}
