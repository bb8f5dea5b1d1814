//! `cellgate status` and `cellgate health`.

use clap::Args;

use super::{ClientCommand, ConnectArgs, Io};
use crate::client::{Client, ClientError, render};
use cellgate_core::pb;

/// `cellgate health`: the probe of containers and service managers.
#[derive(Debug, Clone, Args)]
pub struct HealthArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Healthy when the gateway answers, whatever its links do: for a liveness probe, which
    /// should not restart a gateway because a CNC is switched off.
    #[arg(long)]
    pub gateway_only: bool,
    /// Print JSON (healthy, links, down, alarm) instead of text.
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for HealthArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    /// Connecting already proved that the gateway answers its admin key; then every link
    /// must have its transport open and its device answering. A machine in alarm has its
    /// link up (the board answers), so it is healthy, but named: an operator's matter, not
    /// the gateway's.
    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        if self.gateway_only {
            if self.json {
                let v = serde_json::json!({ "healthy": true, "gateway": true });
                let _ = writeln!(io.out, "{v}");
            } else {
                let _ = writeln!(io.out, "ok: the gateway answers");
            }
            return Ok(0);
        }
        let statuses = client.status(None).await?;
        let plcs = client.plc_status(None).await?;
        let stations: Vec<&pb::PlcStation> = plcs.iter().flat_map(|p| &p.stations).collect();
        let mut down: Vec<String> = statuses
            .iter()
            .filter_map(|s| {
                let state = pb::LinkState::try_from(s.link_state).unwrap_or_default();
                match state {
                    pb::LinkState::Down
                    | pb::LinkState::Connecting
                    | pb::LinkState::Unspecified => {
                        Some(format!("{} ({})", s.machine, render::link_text(state)))
                    }
                    _ => None,
                }
            })
            .collect();
        // A PLC station counts as a link: the gateway cannot read or write it while down.
        down.extend(
            stations
                .iter()
                .filter(|s| !s.up)
                .map(|s| format!("{} station {} (down)", s.plc, s.station)),
        );
        let alarm: Vec<String> = statuses
            .iter()
            .filter(|s| render::in_alarm(s))
            .map(|s| s.machine.clone())
            .collect();
        let links = statuses.len() + stations.len();
        let healthy = down.is_empty();
        if self.json {
            let v = serde_json::json!({
                "healthy": healthy, "gateway": true, "links": links, "down": down,
                "alarm": alarm,
            });
            let _ = writeln!(io.out, "{v}");
        } else if healthy {
            let _ = write!(
                io.out,
                "ok: the gateway answers and its {links} link(s) are up"
            );
            if !alarm.is_empty() {
                let _ = write!(io.out, "; in alarm: {}", alarm.join(", "));
            }
            let _ = writeln!(io.out);
        } else {
            let _ = writeln!(
                io.out,
                "unhealthy: {} of {links} link(s) down: {}",
                down.len(),
                down.join(", ")
            );
        }
        Ok(if healthy { 0 } else { 1 })
    }
}

/// `cellgate status`.
#[derive(Debug, Clone, Args)]
pub struct StatusArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// One machine; default every machine of the cell.
    #[arg(value_name = "MACHINE")]
    pub machine: Option<String>,
    /// Print JSON (an array of MachineStatus, with the .proto's field and enum names).
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for StatusArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let statuses = client.status(self.machine.as_deref()).await?;
        if self.json {
            let all: Vec<_> = statuses.iter().map(render::status_json).collect();
            let text = serde_json::to_string_pretty(&all).unwrap_or_default();
            let _ = writeln!(io.out, "{text}");
        } else {
            let _ = write!(io.out, "{}", render::status_table(&statuses));
        }
        // The PLC stations, when no one machine was asked for.
        if self.machine.is_none() && !self.json {
            let plcs = client.plc_status(None).await.unwrap_or_default();
            let _ = write!(
                io.out,
                "{}",
                render::plc_status_text(&plcs, cellgate_core::pb::now_ms())
            );
        }
        if !self.json
            && let Some(line) = render::gateway_line(client.admin(), cellgate_core::pb::now_ms())
        {
            let _ = writeln!(io.out, "{line}");
        }
        if statuses.is_empty() && client.admin().is_null() {
            // A gateway that hides @admin enforces roles: no status may be a refusal.
            let _ = writeln!(
                io.err,
                "note: this gateway enforces roles; status needs status.read"
            );
        }
        Ok(0)
    }
}
