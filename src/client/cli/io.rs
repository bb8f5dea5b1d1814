//! `cellgate do` and `cellgate di`.

use std::time::Duration;

use clap::Args;

use super::{ClientCommand, ConnectArgs, Io};
use crate::client::{Client, ClientError, parse_byte, render};

fn byte_arg(text: &str) -> Result<u8, String> {
    parse_byte(text)
}

/// After this long without the board's answer, `do` and `di` say on stderr what they wait
/// for: the board speaks only at its next exchange, up to 2·Tp + 1 s away.
const SAY_WAITING_AFTER: Duration = Duration::from_millis(1500);

/// The machine's Tp (the board's SAT polling interval, §4.5) as its cell file sets it, else
/// the board's power-on value.
fn tp_of(client: &Client, machine: &str) -> u64 {
    client.admin()["config"]["machines"]
        .as_array()
        .and_then(|ms| ms.iter().find(|m| m["name"] == machine))
        .and_then(|m| m["tp"].as_u64())
        .unwrap_or(u64::from(cellgate_core::fanuc::sat::Params::POWER_ON.tp))
}

/// Runs `request`, and if it has not ended after [`SAY_WAITING_AFTER`], says on stderr what
/// it waits for and why it takes this long.
async fn saying_why<T>(
    io: &mut Io<'_>,
    client: &Client,
    machine: &str,
    what: &str,
    request: impl std::future::Future<Output = T>,
) -> T {
    tokio::pin!(request);
    tokio::select! {
        done = &mut request => return done,
        () = tokio::time::sleep(SAY_WAITING_AFTER) => {}
    }
    let tp = tp_of(client, machine);
    let _ = writeln!(
        io.err,
        "{machine}: waiting for the remote buffer: the gateway can {what} only at the board's \
         next exchange, which comes every Tp = {tp} s (up to {} s)...",
        2 * tp + 1
    );
    request.await
}

/// `cellgate do`.
#[derive(Debug, Clone, Args)]
pub struct DoArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The machine (Protocol A family only: SDO, §4.4.1).
    #[arg(value_name = "MACHINE")]
    pub machine: String,
    /// The DO bits: 0x.. hex, 0b.. binary or decimal, 0..=255.
    #[arg(value_name = "VALUE", value_parser = byte_arg)]
    pub value: u8,
    /// Which bits to change (same notations); the others keep the last DO image. Default:
    /// all 8.
    #[arg(long, value_name = "MASK", value_parser = byte_arg)]
    pub mask: Option<u8>,
    /// Put the command and return without waiting for SDO to go out (no confirmation).
    #[arg(long)]
    pub no_wait: bool,
    /// Print JSON (machine, do_image, confirmed) instead of text.
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for DoArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        if self.no_wait {
            client.put_do(&self.machine, self.value, self.mask).await?;
            if self.json {
                let v = serde_json::json!({
                    "machine": self.machine, "value": self.value, "mask": self.mask,
                    "confirmed": false,
                });
                let _ = writeln!(io.out, "{v}");
            }
            let _ = writeln!(io.err, "{}: DO command sent (not confirmed)", self.machine);
            return Ok(0);
        }
        let status = saying_why(
            io,
            client,
            &self.machine,
            "output DO (SDO)",
            client.set_do(&self.machine, self.value, self.mask),
        )
        .await?;
        let image = status.do_image.unwrap_or(u32::from(self.value));
        if self.json {
            let v = serde_json::json!({
                "machine": self.machine, "do_image": image, "confirmed": true,
            });
            let _ = writeln!(io.out, "{v}");
        } else {
            let _ = writeln!(io.out, "{} DO {}", self.machine, render::byte_image(image));
        }
        Ok(0)
    }
}

/// `cellgate di`.
#[derive(Debug, Clone, Args)]
pub struct DiArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The machine (Protocol A family only: RDI → SDI, §4.4.1). The read waits for the
    /// board's next exchange, up to 2·Tp + 1 s.
    #[arg(value_name = "MACHINE")]
    pub machine: String,
    /// Print JSON (machine, value, unix_ms) instead of text.
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for DiArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let di = saying_why(
            io,
            client,
            &self.machine,
            "read DI (RDI, answered by SDI)",
            client.read_di(&self.machine),
        )
        .await?;
        if self.json {
            let _ = writeln!(io.out, "{}", render::di_json(&di));
        } else {
            let _ = write!(io.out, "{}", render::di_text(&di));
        }
        Ok(0)
    }
}
