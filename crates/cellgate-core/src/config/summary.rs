//! What `cellgate check-config` prints of a valid cell file: the values in force, defaults
//! filled in, and the CNC parameter values they imply.

use std::fmt::{self, Write as _};

use super::CellConfig;
use super::error::plain_name;
use super::transport::TransportConfig;
use crate::fanuc::{CodeSystem, EndCode, Protocol};
use crate::fuji::frame::BccKind;

impl CellConfig {
    /// A human-readable view of the validated configuration, with the values in force
    /// (defaults filled in) and the CNC parameter values they imply.
    pub fn summary(&self) -> String {
        let mut s = String::new();
        let _ = self.write_summary(&mut s);
        s
    }

    /// The cell's machines and PLCs at a glance, one line each, with what each takes: what
    /// `cellgate run` prints when it serves, so a newcomer knows what to address. At most
    /// `max` lines of machines and PLCs; the rest are counted.
    pub fn overview(&self, max: usize) -> String {
        let mut lines: Vec<(String, String)> = Vec::new();
        for m in &self.machines {
            let p = m.protocol;
            let mut what = p.title().to_string();
            if p == Protocol::ExpansionA {
                let _ = write!(what, " (n = {})", m.effective_packet_n());
            }
            if m.code == CodeSystem::Iso {
                what.push_str(", ISO");
            }
            let _ = write!(what, ", {}: programs (submit)", where_(&m.transport));
            if p.is_a_family() {
                what.push_str(", DI/DO");
            } else {
                what.push_str(", punched programs");
                if m.effective_notify_alarm_reset() {
                    what.push_str(", alarm and reset notices");
                }
            }
            if let Some(g) = &m.g05 {
                let _ = write!(
                    what,
                    ", G05 streams of {} axes at T = {} ms",
                    g.format.axes,
                    g.format.unit_time_ms.ms()
                );
            }
            lines.push((m.name.clone(), what));
        }
        for p in &self.plcs {
            let tags: Vec<String> = p
                .tags
                .iter()
                .map(|t| {
                    if t.writable {
                        format!("{} (writable)", t.name)
                    } else {
                        t.name.clone()
                    }
                })
                .collect();
            // What each mode carries (FFU120B §1-3, §5-2): the command set reads and writes
            // memory, transfers only in mode 1 (1:1); modes 4 and 5 carry messages only.
            let carries = match p.mode {
                1 => "memory, transfers".to_string(),
                2 | 3 => "memory".to_string(),
                _ => match p.fixed_length.filter(|n| *n != 0) {
                    Some(n) => format!(
                        "messages of {n} bytes both ways, to receive message {}",
                        p.receive_message
                    ),
                    None => format!(
                        "messages both ways (variable length), to receive message {}",
                        p.receive_message
                    ),
                },
            };
            let mut what = format!(
                "MICREX-F PLC, FFU120B mode {}, {}: {carries}",
                p.mode,
                where_(&p.transport)
            );
            if !tags.is_empty() {
                let _ = write!(what, ", tags {}", tags.join(", "));
            }
            lines.push((p.name.clone(), what));
        }
        let width = lines
            .iter()
            .map(|(n, _)| n.chars().count())
            .max()
            .unwrap_or(0);
        let mut out = String::new();
        for (name, what) in lines.iter().take(max) {
            let _ = writeln!(out, "  {name:<width$}  {what}");
        }
        if lines.len() > max {
            let _ = writeln!(out, "  ... and {} more", lines.len() - max);
        }
        out
    }

    fn write_summary(&self, s: &mut String) -> fmt::Result {
        writeln!(s, "cell {}", self.cell)?;
        let b = &self.bus;
        let list = |v: &[String]| {
            if v.is_empty() {
                "none".to_string()
            } else {
                v.join(", ")
            }
        };
        writeln!(
            s,
            "bus: {} mode, keys under {}/{}, listen {}, connect {}, multicast scouting {}",
            plain_name(&b.mode),
            b.prefix,
            self.cell,
            list(&b.listen),
            list(&b.connect),
            on_off(b.multicast_scouting),
        )?;
        if let Some(z) = &b.zenoh_config {
            writeln!(s, "  zenoh config file {}", z.display())?;
        }
        let t = &self.telemetry;
        writeln!(
            s,
            "telemetry: {} logs, filter {:?}, OTLP export {}, Prometheus endpoint {}",
            plain_name(&t.log_format),
            t.log_filter,
            t.otlp_endpoint.as_deref().map_or_else(
                || "off".to_string(),
                |e| format!(
                    "to {} as {:?}",
                    super::telemetry::redact_credentials(e),
                    t.service_name
                )
            ),
            t.prometheus
                .as_deref()
                .map_or_else(|| "off".to_string(), |a| format!("on {a}/metrics")),
        )?;
        writeln!(
            s,
            "programs: in {}, at most {} each; punched programs {}; remote requests {}",
            self.programs.dir.display(),
            show_size(self.programs.max_size),
            if self.programs.store_punched {
                "stored"
            } else {
                "not stored"
            },
            if self.programs.requests.is_empty() {
                "off".to_string()
            } else {
                self.programs.requests.join(" ")
            }
        )?;
        writeln!(
            s,
            "  job journal in {}, {} ended jobs kept per machine",
            self.programs.journal_dir().display(),
            self.programs.keep_jobs
        )?;
        let p = &self.programs;
        if p.quota_bytes.is_some() || p.quota_files.is_some() || p.punched_retention_days.is_some()
        {
            writeln!(
                s,
                "  quota: {}, {}; punched programs kept {}",
                p.quota_bytes
                    .map_or("bytes unbounded".to_string(), |b| format!(
                        "{} in all",
                        show_size(b)
                    )),
                p.quota_files
                    .map_or("files unbounded".to_string(), |f| format!("{f} programs")),
                p.punched_retention_days
                    .map_or("until removed".to_string(), |d| format!("{d} days")),
            )?;
        }
        self.write_security(s)?;
        writeln!(s, "machines: {}", self.machines.len())?;
        for m in &self.machines {
            let p = m.protocol;
            write!(s, "  {}: {}", m.name, p.title())?;
            if p == Protocol::ExpansionA {
                let n = m.effective_packet_n();
                write!(s, " n = {n} ({}-byte packets)", 256 * u32::from(n))?;
            }
            writeln!(
                s,
                ", {} code (5000#2 = {}), {}",
                match m.code {
                    CodeSystem::Ascii => "ASCII",
                    CodeSystem::Iso => "ISO",
                },
                m.code.param_5000_bit2(p),
                m.effective_interface().name(),
            )?;
            if p.is_a_family() {
                writeln!(
                    s,
                    "    end code {} (5000#3 = {})",
                    match m.effective_end_code() {
                        EndCode::Cr => "CR",
                        EndCode::Etx => "ETX",
                    },
                    m.param_5000_bit3()
                )?;
            } else {
                writeln!(
                    s,
                    "    reset/alarm notification {} (5000#3 = {})",
                    on_off(m.effective_notify_alarm_reset()),
                    m.param_5000_bit3()
                )?;
            }
            writeln!(
                s,
                "    transport: {}",
                m.transport.describe_with(m.tcp_window())
            )?;
            if let TransportConfig::Sim { .. } = m.transport {
                let b = m.board_sim();
                writeln!(
                    s,
                    "    simulated board: buffer {} bytes, CNC takes {} bytes/s, {} axes",
                    b.buffer_size, b.consume_rate, b.axes
                )?;
            }
            // SET and the §4.5 timers exist in the Protocol A family only.
            if p.is_a_family() {
                writeln!(s, "    parameters: {}", m.params())?;
            }
            if let Some(g) = &m.g05 {
                writeln!(
                    s,
                    "    {}",
                    g.describe_on(m.transport.line(), m.g05_refill())
                )?;
            }
        }
        writeln!(s, "plcs: {}", self.plcs.len())?;
        for p in &self.plcs {
            let stations: Vec<String> = p.stations.iter().map(|n| format!("{n:02}")).collect();
            writeln!(
                s,
                "  {}: FFU120B mode {}, stations {}",
                p.name,
                p.mode,
                stations.join(", ")
            )?;
            writeln!(
                s,
                "    start code {}, end code {}, code transposition {}, reply time-out {} ms",
                show_bytes(p.frame.start_bytes()),
                show_bytes(p.frame.end_bytes()),
                on_off(p.frame.transposition),
                p.timeout_ms
            )?;
            if p.frame.bcc == BccKind::None {
                writeln!(s, "    BCC none")?;
            } else {
                writeln!(
                    s,
                    "    BCC {} ({}, {}), over {}, as {}",
                    plain_name(&p.frame.bcc_calc),
                    plain_name(&p.frame.bcc),
                    if p.frame.bcc == BccKind::Set1 {
                        "high byte first"
                    } else {
                        "low byte first"
                    },
                    plain_name(&p.frame.bcc_range),
                    plain_name(&p.frame.bcc_code)
                )?;
            }
            writeln!(s, "    transport: {}", p.transport.describe())?;
            self.write_tags(s, p)?;
        }
        self.write_served(s)
    }

    /// A PLC's tags, one line each: where it lives, how it reads, how often, who may write.
    fn write_tags(&self, s: &mut String, p: &super::PlcConfig) -> fmt::Result {
        if p.tags.is_empty() {
            return writeln!(s, "    tags: none");
        }
        writeln!(s, "    tags: {}", p.tags.len())?;
        for t in &p.tags {
            write!(s, "      {}: {}{}", t.name, t.module, t.address)?;
            match t.bit {
                Some(bit) => write!(s, " bit {bit}")?,
                None => write!(s, " {}", plain_name(&t.kind))?,
            }
            if t.scale.0 != 1.0 {
                write!(s, " × {}", t.scale.0)?;
            }
            write!(s, ", station {:02}", t.station)?;
            write!(s, ", read every {} ms", t.poll_ms)?;
            if t.deadband.0 != 0.0 {
                write!(s, ", deadband {}", t.deadband.0)?;
            }
            write!(s, ", {}", if t.writable { "writable" } else { "read-only" })?;
            if t.history {
                write!(s, ", values kept in the history")?;
            }
            writeln!(s)?;
        }
        Ok(())
    }

    /// The console and the MTConnect agent the gateway serves, or that it serves none.
    fn write_served(&self, s: &mut String) -> fmt::Result {
        match &self.console {
            None => writeln!(s, "console: none (no [console])")?,
            Some(c) => {
                write!(
                    s,
                    "console: on {} ({}), sessions end after {} min idle and {} h at most, {} \
                     per user",
                    c.listen,
                    if self.security.tls.is_some() {
                        "HTTPS with the cell's certificate"
                    } else {
                        "HTTP"
                    },
                    c.session_idle_minutes,
                    c.session_hours,
                    c.sessions_per_user
                )?;
                if !c.host_names.is_empty() {
                    write!(s, "; also reached as {}", c.host_names.join(", "))?;
                }
                if c.allow_remote {
                    write!(s, "; beyond loopback without [security] (allow_remote)")?;
                }
                writeln!(s)?;
            }
        }
        match &self.mtconnect {
            None => writeln!(s, "mtconnect: none (no [mtconnect])"),
            Some(m) => writeln!(
                s,
                "mtconnect: agent on {} (HTTP), {} observations kept, {}",
                m.listen,
                m.buffer_size,
                m.shdr_listen.as_deref().map_or_else(
                    || "no SHDR adapter".to_string(),
                    |a| format!("SHDR adapter on {a}")
                )
            ),
        }
    }
}

impl CellConfig {
    fn write_security(&self, s: &mut String) -> fmt::Result {
        let sec = &self.security;
        if sec.is_empty() {
            return writeln!(
                s,
                "security: none: any session that reaches the gateway may do anything"
            );
        }
        match &sec.tls {
            Some(t) => writeln!(
                s,
                "security: TLS with CA {}, certificate {}, key {}; client certificates {}; \
                 router names {}",
                t.ca.display(),
                t.certificate.display(),
                t.private_key.display(),
                if t.require_client_certificates {
                    "required"
                } else {
                    "not asked for"
                },
                if t.verify_name_on_connect {
                    "verified"
                } else {
                    "not verified"
                },
            )?,
            None => writeln!(s, "security: no TLS")?,
        }
        if let Some(f) = &sec.users_file {
            writeln!(s, "  user names and passwords from {}", f.display())?;
        }
        if sec.roles.is_empty() {
            return writeln!(
                s,
                "  roles: none: every client that connects may do anything"
            );
        }
        writeln!(
            s,
            "  roles ({}; what no role allows is denied):",
            sec.roles.len()
        )?;
        for r in &sec.roles {
            let mut who = Vec::new();
            if !r.cert_common_names.is_empty() {
                who.push(format!("certificates {}", r.cert_common_names.join(", ")));
            }
            if !r.usernames.is_empty() {
                who.push(format!("users {}", r.usernames.join(", ")));
            }
            let what: Vec<&str> = r.permissions.iter().map(|p| p.name()).collect();
            writeln!(s, "    {}: {}: {}", r.name, who.join("; "), what.join(", "))?;
        }
        Ok(())
    }
}

pub(super) fn show_size(bytes: u64) -> String {
    const MIB: u64 = 1024 * 1024;
    if bytes >= MIB && bytes % MIB == 0 {
        format!("{} MiB", bytes / MIB)
    } else if bytes >= 1024 && bytes % 1024 == 0 {
        format!("{} KiB", bytes / 1024)
    } else {
        format!("{bytes} bytes")
    }
}

pub(super) fn on_off(b: bool) -> &'static str {
    if b { "on" } else { "off" }
}

pub(super) fn show_bytes(b: &[u8]) -> String {
    if b.is_empty() {
        return "none".to_string();
    }
    let names: Vec<String> = b
        .iter()
        .map(|&c| match c {
            0x02 => "STX".to_string(),
            0x03 => "ETX".to_string(),
            0x0A => "LF".to_string(),
            0x0D => "CR".to_string(),
            0x10 => "DLE".to_string(),
            0x21..=0x7E => format!("'{}'", char::from(c)),
            _ => format!("{c:02X}h"),
        })
        .collect();
    names.join(" ")
}

/// Where a link goes, in a few words: `simulated, 19200 baud`, `serial /dev/ttyS0`,
/// `tcp 192.0.2.21:4001`.
fn where_(t: &TransportConfig) -> String {
    match t {
        TransportConfig::Sim { line } => format!("simulated, {} baud", line.baud),
        TransportConfig::Serial { path, line, .. } => format!("serial {path}, {} baud", line.baud),
        TransportConfig::Tcp { address, line, .. } => format!("tcp {address}, {} baud", line.baud),
    }
}
