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

use std::time::Duration;

use serde::de::{self, MapAccess, Visitor};
use serde::{Deserialize, Deserializer, Serialize};

use super::error::{Checker, q};
use crate::engine::LineSettings;
use crate::fanuc::Protocol;
use crate::fanuc::g05::{G05Entry, G05Format, required_baud};
use crate::fanuc::sat::Params;

/// The credit window holds at least this many bytes of blocks, so that a whole DAT or data
/// packet can always be filled (min(4096, Nb − No), §4.4.2 3; 256·n, §5.2) while another is on
/// the line: a window smaller than a DAT would make every GTD wait.
pub const MIN_WINDOW_BYTES: u32 = 8192;

/// Characters of a Protocol A message around its data part: checksum (2), command (3), end
/// code (1) (§4.1; protocol notes 1). The board's GTD is one such message without data.
const MESSAGE_FRAME: u64 = 6;
/// Characters of an Expansion A data packet around its data: packet number (1), checksum
/// (2), CR (1) (§5.2; protocol notes 9).
const PACKET_FRAME: u64 = 4;

/// How a board that uses data only in whole pieces is refilled while a G05 stream runs
/// (§9.2): the board stores a DAT (Protocol A, §4.4.2 3) or a data packet (Expansion A,
/// §5.2) only once all of it has arrived, so the CNC cannot read a block before the whole
/// piece carrying it is in, and the blocks it holds must last until the next piece is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Refill {
    /// `"DAT"` or `"data packet"`.
    pub piece: &'static str,
    /// Program bytes in the longest piece: min(4096, Nb − No) for a DAT, 256·n for a packet.
    pub data: usize,
    /// From the moment the board has one piece to the moment it can have the next longest one
    /// whole: for a DAT, the board's Tx and its GTD (Ti between its characters), then the DAT
    /// on the line; for a packet, the packet on the line (the host sends them back to back).
    pub time: Duration,
}

impl Refill {
    /// The refill of a board of `protocol` with the §4.5 `params` and packet length `n`
    /// (the cell file's: the host sets them by SET), on `line`; `None` where the CNC reads the
    /// bytes as they come (Protocol B and Expansion B).
    pub fn of(protocol: Protocol, params: Params, n: u8, line: &LineSettings) -> Option<Refill> {
        match protocol {
            Protocol::A => {
                let data = usize::from(params.nb.saturating_sub(params.no))
                    .clamp(1, crate::fanuc::message::MAX_DAT_DATA);
                let chars = 2 * MESSAGE_FRAME + data as u64;
                let board = Duration::from_millis(
                    u64::from(params.tx) + (MESSAGE_FRAME - 1) * u64::from(params.ti),
                );
                Some(Refill {
                    piece: "DAT",
                    data,
                    time: board + line.time_for_chars(chars),
                })
            }
            Protocol::ExpansionA => {
                let data = 256 * usize::from(n.max(1));
                Some(Refill {
                    piece: "data packet",
                    data,
                    time: line.time_for_chars(data as u64 + PACKET_FRAME),
                })
            }
            _ => None,
        }
    }
}

/// G05 binary input on a machine (`[machines.g05]`): the CNC's [`G05Format`], whose five
/// keys sit in the table beside the stream's own (see [`G05Format`] for what each means and
/// [`G05Format::new`] for the defaults of all but `axes`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct G05Config {
    /// The block format the CNC's parameters set (§9.1, §10.3).
    #[serde(flatten)]
    pub format: G05Format,
    /// NC text sent before the binary blocks; its last block is the `G05` block (protocol
    /// notes 15).
    pub before: String,
    /// NC text sent after the end block; the program's EOR follows it.
    pub after: String,
    /// Blocks the gateway holds for a stream (its credit window), as time at one block per T;
    /// raised to `MIN_WINDOW_BYTES` of blocks.
    pub window_ms: u32,
    /// Blocks buffered before the `G05` block goes out: the CNC takes a block every T from the
    /// moment it reads `G05` (§9.1 (2)).
    pub prime_ms: u32,
    /// A producer that sends nothing for this long while the CNC's buffer is estimated empty
    /// is taken as gone: the stream ends with the end block.
    pub idle_ms: u32,
}

impl G05Config {
    /// A stream of blocks in `format`, with the stream's defaults: `before = "G05\n"`, no
    /// `after`, a window of 1 s, priming 500 ms, a producer gone after 2 s.
    pub fn new(format: G05Format) -> Self {
        G05Config {
            format,
            before: "G05\n".to_string(),
            after: String::new(),
            window_ms: 1000,
            prime_ms: 500,
            idle_ms: 2000,
        }
    }

    /// The block format (a copy, for the engine).
    pub const fn format(&self) -> G05Format {
        self.format
    }

    fn blocks_in(&self, ms: u32) -> u32 {
        (ms / self.format.unit_time_ms.ms()).max(1)
    }

    /// The credit window in blocks: `window_ms` of blocks, at least `MIN_WINDOW_BYTES`.
    pub fn window_blocks(&self) -> u32 {
        let block = self.format().block_len() as u32;
        self.blocks_in(self.window_ms)
            .max(MIN_WINDOW_BYTES.div_ceil(block.max(1)))
    }

    /// The priming level in blocks (never above the window).
    pub fn prime_blocks(&self) -> u32 {
        self.blocks_in(self.prime_ms).min(self.window_blocks())
    }

    /// Whole blocks in `bytes` of the stream's program after `before`.
    fn blocks_of(&self, bytes: usize) -> u64 {
        let block = self.format().block_len().max(1);
        (bytes / block) as u64
    }

    /// The priming level in blocks on a board refilled as `refill` says: `prime_ms` of
    /// blocks, raised so that they last the CNC, from the moment it reads the `G05` block,
    /// until the next longest piece can have arrived whole, plus one unit time for the phase
    /// of the CNC's clock (§9.2). Without it a stream opened while the CNC waits got a first
    /// DAT with 500 ms of blocks followed by a 1931-byte one taking 553 ms at 38 400 baud.
    /// (The first piece carries as many of them as fit; see [`G05Config::standing_start`].)
    pub fn prime_blocks_on(&self, refill: Option<Refill>) -> u32 {
        let t = self.format.unit_time_ms.duration();
        let needed = refill.map_or(0, |r| {
            u32::try_from(r.time.as_nanos().div_ceil(t.as_nanos().max(1)))
                .unwrap_or(u32::MAX)
                .saturating_add(1)
        });
        self.prime_blocks().max(needed).min(self.window_blocks())
    }

    /// Why a stream started while the CNC waits would run dry on a board refilled as
    /// `refill` says, whatever the priming: the first piece holds the `G05` block and as
    /// many blocks as fit, and they run out before the next piece can be whole; or a piece
    /// brings the CNC less time than its exchange takes, so every stream runs dry once what
    /// the board held is used. `None` when neither happens.
    pub fn standing_start(&self, refill: Option<Refill>) -> Option<String> {
        let r = refill?;
        let t = self.format.unit_time_ms.duration();
        let ms = |d: Duration| d.as_secs_f64() * 1000.0;
        let steady = self.blocks_of(r.data);
        if t * u32::try_from(steady).unwrap_or(u32::MAX) < r.time {
            return Some(format!(
                "G05 cannot keep up on this line: a {} of {} bytes brings the CNC {steady} blocks, \
                 {:.0} ms at T = {} ms, but the next one takes {:.0} ms to arrive whole (§9.2, \
                 §4.4.2, §5.2): every stream runs dry; raise the baud rate, Nb − No or n, or \
                 lower Tx and Ti",
                r.piece,
                r.data,
                ms(t * u32::try_from(steady).unwrap_or(u32::MAX)),
                t.as_millis(),
                ms(r.time),
            ));
        }
        let first = self.blocks_of(r.data.saturating_sub(self.before.len()));
        let lasts = t * u32::try_from(first).unwrap_or(u32::MAX);
        if lasts < r.time {
            return Some(format!(
                "a G05 stream started while the CNC waits runs dry: the board uses a {} only \
                 once all of it has arrived, and the first one ({} bytes: `before` and {first} \
                 blocks, {:.0} ms at T = {} ms) runs out before the next can be whole ({:.0} ms) \
                 (§9.2)",
                r.piece,
                r.data,
                ms(lasts),
                t.as_millis(),
                ms(r.time),
            ));
        }
        None
    }

    /// The §9.2 requirement on a line framed as `line`.
    pub fn required_baud(&self, line: &LineSettings) -> u32 {
        required_baud(&self.format(), line.bits_per_char())
    }

    /// One line for `check-config` and the start-up log, with the priming in force on a
    /// board refilled as `refill` says.
    pub fn describe_on(&self, line: &LineSettings, refill: Option<Refill>) -> String {
        let mut s = self.describe(line);
        let prime = self.prime_blocks_on(refill);
        if let Some(r) = refill
            && prime > self.prime_blocks()
        {
            s.push_str(&format!(
                " raised to {prime}: they last until the next {} can be whole ({:.0} ms)",
                r.piece,
                r.time.as_secs_f64() * 1000.0
            ));
        }
        s
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

/// The keys of a `[machines.g05]` table: the format's five, then the stream's. The table is
/// read key by key rather than with `#[serde(flatten)]`, which buffers the table and so loses
/// an unknown key's line and the list of known keys that `check-config` reports.
#[derive(Deserialize)]
#[serde(field_identifier, rename_all = "snake_case")]
enum Key {
    Axes,
    DataFormat,
    Aux,
    UnitTimeMs,
    AuxOrder,
    Before,
    After,
    WindowMs,
    PrimeMs,
    IdleMs,
}

impl<'de> Deserialize<'de> for G05Config {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Table;
        impl<'de> Visitor<'de> for Table {
            type Value = G05Config;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a g05 table")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<G05Config, A::Error> {
                let mut axes = None;
                let mut g = G05Config::new(G05Format::new(0));
                while let Some(key) = map.next_key()? {
                    match key {
                        Key::Axes => axes = Some(map.next_value()?),
                        Key::DataFormat => g.format.data_format = map.next_value()?,
                        Key::Aux => g.format.aux = map.next_value()?,
                        Key::UnitTimeMs => g.format.unit_time_ms = map.next_value()?,
                        Key::AuxOrder => g.format.aux_order = map.next_value()?,
                        Key::Before => g.before = map.next_value()?,
                        Key::After => g.after = map.next_value()?,
                        Key::WindowMs => g.window_ms = map.next_value()?,
                        Key::PrimeMs => g.prime_ms = map.next_value()?,
                        Key::IdleMs => g.idle_ms = map.next_value()?,
                    }
                }
                g.format.axes = axes.ok_or_else(|| de::Error::missing_field("axes"))?;
                Ok(g)
            }
        }
        deserializer.deserialize_map(Table)
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
                g.format.axes,
                g.format.data_format.name()
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
                g.format.axes,
                if g.format.aux.rax() {
                    " and the auxiliary word"
                } else {
                    ""
                },
                g.format.unit_time_ms.ms(),
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
