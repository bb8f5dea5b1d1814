//! The PLCs as `cellgate plc status` prints them.

use std::fmt::Write as _;

use cellgate_core::pb;

use super::last_error_text;

pub fn plc_status_text(plcs: &[pb::PlcStatus], now_ms: u64) -> String {
    let mut s = String::new();
    if plcs.is_empty() {
        return s;
    }
    let _ = writeln!(
        s,
        "{:<12} {:>7} {:<5} {:>9} {:>9} {:>8} {:>7} {:>4}  LAST ERROR",
        "PLC", "STATION", "STATE", "REQUESTS", "REPLIES", "TIMEOUTS", "RETRIES", "BCC"
    );
    for p in plcs {
        for st in &p.stations {
            let _ = writeln!(
                s,
                "{:<12} {:>7} {:<5} {:>9} {:>9} {:>8} {:>7} {:>4}  {}",
                p.plc,
                format!("{:02}", st.station),
                if st.up { "up" } else { "down" },
                st.requests,
                st.replies,
                st.timeouts,
                st.retries,
                st.bcc_errors,
                last_error_text(st, now_ms)
            );
        }
    }
    for p in plcs {
        // A noisy line shows here (FFU120B §5-6): characters with errors, texts dropped.
        let counts = |m: &std::collections::HashMap<String, u64>| {
            let mut v: Vec<(&String, &u64)> = m.iter().filter(|(_, n)| **n > 0).collect();
            v.sort();
            v.iter()
                .map(|(k, n)| format!("{k} {n}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        let (line, dropped) = (counts(&p.line_errors), counts(&p.receive_errors));
        if !line.is_empty() || !dropped.is_empty() {
            let none = || "none".to_string();
            let _ = writeln!(
                s,
                "{}: line errors: {}; texts dropped: {}",
                p.plc,
                if line.is_empty() { none() } else { line },
                if dropped.is_empty() { none() } else { dropped }
            );
        }
    }
    for p in plcs {
        for g in &p.poll_groups {
            let _ = writeln!(
                s,
                "{}: poll group {} every {} ms, {} reads: round {} ms (mean {}, max {}), achieved interval {} ms, {} overruns in {} rounds",
                p.plc,
                g.group,
                g.interval_ms,
                g.reads,
                g.last_round_ms,
                g.mean_round_ms,
                g.max_round_ms,
                g.achieved_interval_ms,
                g.overruns,
                g.rounds
            );
        }
    }
    s
}
