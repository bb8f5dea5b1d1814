//! The `g05` table of a machine: G05 binary input (§9, §10.3).
//!
//! ```toml
//! [machines.g05]
//! axes = 3                 # parameter 7635
//! data_format = "special"  # 7609#2 RDS: "special" (required by Protocol A) or "general"
//! aux = "none"             # 7609#3 RAX and 2034: "none", "second", "m", "s", "t"
//! unit_time_ms = 8         # 7618: 1, 2, 4, 8 or 16
//! aux_order = "high-first" # or "low-first" (protocol notes 14)
//! before = "G05\n"         # NC text before the blocks, ending with the G05 block
//! after = "M30\n"          # NC text after the end block (EOR is added)
//! window_ms = 1000         # blocks the gateway holds, as time at one per T (8 KiB at least)
//! prime_ms = 500           # blocks held before the G05 block goes out
//! idle_ms = 2000           # a producer silent this long while the CNC runs dry ends the stream
//! ```

use serde::{Deserialize, Serialize};

use super::error::{Checker, q};
use crate::engine::LineSettings;
use crate::fanuc::Protocol;
use crate::fanuc::g05::{
    AuxFunction, AuxOrder, DataFormat, G05Entry, G05Format, UnitTime, required_baud,
};

/// The credit window holds at least this many bytes of blocks, so that a whole DAT or data
/// packet can always be filled (min(4096, Nb − No), §4.4.2 3; 256·n, §5.2) while another is on
/// the line: a window smaller than a DAT would make every GTD wait.
pub const MIN_WINDOW_BYTES: u32 = 8192;

/// G05 binary input on a machine (`[machines.g05]`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct G05Config {
    /// Parameter 7635: axes in a block.
    pub axes: u8,
    /// Parameter 7609#2 RDS: how travels and the auxiliary word are written (default `special`).
    #[serde(default)]
    pub data_format: DataFormat,
    /// Parameters 7609#3 RAX and 2034: the auxiliary word and its function (default `none`).
    #[serde(default)]
    pub aux: AuxFunction,
    /// Parameter 7618: the unit time T, one block per T: 1, 2, 4, 8 or 16 ms (default 8).
    #[serde(default)]
    pub unit_time_ms: UnitTime,
    /// Order of the auxiliary word's halves on the line (protocol notes 14; default `high-first`).
    #[serde(default)]
    pub aux_order: AuxOrder,
    /// NC text sent before the binary blocks; its last block is the `G05` block (protocol
    /// notes 15).
    #[serde(default = "G05Config::default_before")]
    pub before: String,
    /// NC text sent after the end block; the program's EOR follows it.
    #[serde(default)]
    pub after: String,
    /// Blocks the gateway holds for a stream (its credit window), as time at one block per T;
    /// raised to [`MIN_WINDOW_BYTES`] of blocks.
    #[serde(default = "G05Config::default_window_ms")]
    pub window_ms: u32,
    /// Blocks buffered before the `G05` block goes out: the CNC takes a block every T from the
    /// moment it reads `G05` (§9.1 (2)).
    #[serde(default = "G05Config::default_prime_ms")]
    pub prime_ms: u32,
    /// A producer that sends nothing for this long while the CNC's buffer is estimated empty
    /// is taken as gone: the stream ends with the end block.
    #[serde(default = "G05Config::default_idle_ms")]
    pub idle_ms: u32,
}

impl G05Config {
    fn default_before() -> String {
        "G05\n".to_string()
    }
    const fn default_window_ms() -> u32 {
        1000
    }
    const fn default_prime_ms() -> u32 {
        500
    }
    const fn default_idle_ms() -> u32 {
        2000
    }

    /// The block format.
    pub fn format(&self) -> G05Format {
        G05Format {
            axes: self.axes,
            data_format: self.data_format,
            aux: self.aux,
            unit_time_ms: self.unit_time_ms,
            aux_order: self.aux_order,
        }
    }

    fn blocks_in(&self, ms: u32) -> u32 {
        (ms / self.unit_time_ms.ms()).max(1)
    }

    /// The credit window in blocks: `window_ms` of blocks, at least [`MIN_WINDOW_BYTES`].
    pub fn window_blocks(&self) -> u32 {
        let block = self.format().block_len() as u32;
        self.blocks_in(self.window_ms)
            .max(MIN_WINDOW_BYTES.div_ceil(block.max(1)))
    }

    /// The priming level in blocks (never above the window).
    pub fn prime_blocks(&self) -> u32 {
        self.blocks_in(self.prime_ms).min(self.window_blocks())
    }

    /// The §9.2 requirement on a line framed as `line`.
    pub fn required_baud(&self, line: &LineSettings) -> u32 {
        required_baud(&self.format(), line.bits_per_char())
    }

    /// One line for `check-config` and the start-up log.
    pub fn describe(&self, line: &LineSettings) -> String {
        let f = self.format();
        let need = self.required_baud(line);
        let ratio = f64::from(line.baud) / f64::from(need.max(1));
        let margin = if ratio < 1.1 {
            " — less than 10 % above the requirement: any delay starves the CNC (§9.2)"
        } else {
            ""
        };
        format!(
            "G05: {} axes, {} format, aux {}, T = {} ms, {}-byte blocks; needs {need} baud, \
             the line runs {:.2}× that{margin}; window {} blocks, priming {}",
            f.axes,
            f.data_format.name(),
            f.aux.name(),
            f.unit_time_ms.ms(),
            f.block_len(),
            ratio,
            self.window_blocks(),
            self.prime_blocks(),
        )
    }
}

/// Checks a machine's `g05` table against its protocol, line and simulated CNC.
pub(super) fn check_g05(
    c: &mut Checker,
    label: &str,
    g: &G05Config,
    protocol: Protocol,
    line: &LineSettings,
    controlled_axes: Option<u8>,
) {
    let path = format!("{label}.g05");
    for problem in g.format().validate_for(protocol, controlled_axes) {
        c.invalid(
            path.clone(),
            format!(
                "axes = {}, data_format = {:?}",
                g.axes,
                g.data_format.name()
            ),
            problem.to_string(),
            "§9.1, §10.3",
        );
    }
    let need = g.required_baud(line);
    if line.baud < need {
        c.invalid(
            format!("{label}.transport.line.baud"),
            line.baud.to_string(),
            format!(
                "G05 with {} axes{} every {} ms needs at least {need} baud ((2·N + n) × {} bits \
                 ÷ T); the CNC would wait for every block",
                g.axes,
                if g.aux.rax() {
                    " and the auxiliary word"
                } else {
                    ""
                },
                g.unit_time_ms.ms(),
                line.bits_per_char(),
            ),
            "§9.2",
        );
    }
    let mut entry = G05Entry::default();
    let entered = g.before.bytes().fold(false, |_, b| entry.feed(b));
    if !entered {
        c.invalid(
            format!("{path}.before"),
            q(&g.before),
            "must end with the G05 block (e.g. \"G05\\n\"), ended by LF or ';'".to_string(),
            "§9.1, protocol notes 15",
        );
    }
    for (key, text) in [("before", &g.before), ("after", &g.after)] {
        if text.contains('%') {
            c.invalid(
                format!("{path}.{key}"),
                q(text),
                "must not hold '%': EOR would end the program there (the gateway adds it \
                 after the end)"
                    .to_string(),
                "§8.2",
            );
        }
    }
    c.range(
        || format!("{path}.window_ms"),
        g.window_ms,
        10,
        60_000,
        " ms",
        "",
    );
    c.range(
        || format!("{path}.prime_ms"),
        g.prime_ms,
        1,
        g.window_ms.max(1),
        " ms (window_ms or less)",
        "",
    );
    c.range(
        || format!("{path}.idle_ms"),
        g.idle_ms,
        10,
        3_600_000,
        " ms",
        "",
    );
}
