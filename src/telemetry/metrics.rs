//! The gateway's counters and how they reach OpenTelemetry.
//!
//! Links, job managers and G05 streams count into plain atomics here ([`link`],
//! [`machine`], [`plc_station_timeout`]), from the typed events they already handle: a relaxed
//! atomic add per pump step or per event, nothing allocated, whether or not anything is
//! exported. The counters are process-wide, like the tracing subscriber, so that every task
//! reaches them without a handle threaded through its arguments, and a link started again
//! under the same name keeps counting up (counters must be monotonic).
//!
//! [`super::install_metrics`] builds a meter provider whose observable instruments read
//! those atomics at collection time (an OTLP export every `OTEL_METRIC_EXPORT_INTERVAL`, a
//! Prometheus scrape), so the cost of exporting is paid by the exporter, not by the line.
//! Job durations and DO delays are the synchronous instruments: a histogram cannot be
//! observed, and each is recorded once per job or per DO command.
//!
//! | instrument | kind | attributes |
//! |---|---|---|
//! | `cellgate.link.io` (By) | counter | `link`, `direction` (`in`/`out`) |
//! | `cellgate.link.frames` | counter | `link`, `direction` |
//! | `cellgate.link.retries` | counter | `link` |
//! | `cellgate.link.checksum_errors` | counter | `link` |
//! | `cellgate.link.line_errors` | counter | `link` |
//! | `cellgate.link.alarms` | counter | `link` |
//! | `cellgate.link.sessions` | counter | `link` |
//! | `cellgate.jobs.queue_depth` | gauge | `machine` |
//! | `cellgate.jobs.ended` | counter | `machine`, `outcome` (`completed`/`failed`/`cancelled`) |
//! | `cellgate.job.duration` (s) | histogram | `machine`, `outcome` |
//! | `cellgate.do.delay` (s) | histogram | `link` |
//! | `cellgate.g05.underruns` | counter | `machine` |
//! | `cellgate.plc.station_timeouts` | counter | `plc`, `station` |
//! | `cellgate.bus.misdirected_writes` | counter | `key` (the read key's kind: `program`, `job`, `plc.tag`, `plc.mem`, `plc.transfer`, `plc.message`) |
//! | `cellgate.history.dropped` | counter | `log` (`history`/`audit`), `reason` |
//! | `cellgate.console.login_failures` | counter | `outcome` (`refused`/`throttled`) |
//! | `cellgate.listen.refused` | counter | `listener` (`console`/`mtconnect`/`shdr`) |
//! | `cellgate.historian.records` | counter | `cell`, `log` (`history`/`audit`) |
//! | `cellgate.historian.failures` | counter | `cell`, `log` |
//! | `cellgate.historian.lag` | gauge | `cell`, `log`: records the gateway holds and the database not yet |

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock, PoisonError};
use std::time::Duration;

use opentelemetry::KeyValue;
use opentelemetry::metrics::{Histogram, Meter, MeterProvider as _};
use opentelemetry_sdk::metrics::SdkMeterProvider;

/// The instrumentation scope of every instrument.
pub const SCOPE: &str = "cellgate";

/// One link's line counters (a FANUC machine's link or a PLC's).
#[derive(Debug)]
pub struct LinkMetrics {
    attrs: [KeyValue; 1],
    bytes_in: AtomicU64,
    bytes_out: AtomicU64,
    frames_in: AtomicU64,
    frames_out: AtomicU64,
    retries: AtomicU64,
    checksum_errors: AtomicU64,
    line_errors: AtomicU64,
    alarms: AtomicU64,
    sessions: AtomicU64,
}

impl LinkMetrics {
    fn new(name: &str) -> Self {
        LinkMetrics {
            attrs: [KeyValue::new("link", name.to_string())],
            bytes_in: AtomicU64::new(0),
            bytes_out: AtomicU64::new(0),
            frames_in: AtomicU64::new(0),
            frames_out: AtomicU64::new(0),
            retries: AtomicU64::new(0),
            checksum_errors: AtomicU64::new(0),
            line_errors: AtomicU64::new(0),
            alarms: AtomicU64::new(0),
            sessions: AtomicU64::new(0),
        }
    }

    /// Bytes read from and written to the line.
    pub fn add_bytes(&self, received: u64, sent: u64) {
        add(&self.bytes_in, received);
        add(&self.bytes_out, sent);
    }

    /// Protocol frames (messages, packets, control codes) received and sent.
    pub fn add_frames(&self, received: u64, sent: u64) {
        add(&self.frames_in, received);
        add(&self.frames_out, sent);
    }

    /// A message sent again, at the board's request or ours.
    pub fn retry(&self) {
        add(&self.retries, 1);
    }

    /// A received frame with a bad checksum (BCC).
    pub fn checksum_error(&self) {
        add(&self.checksum_errors, 1);
    }

    /// A character error on the line (parity, framing, overrun).
    pub fn line_error(&self) {
        add(&self.line_errors, 1);
    }

    /// A link alarm (the link re-initialised or failed).
    pub fn alarm(&self) {
        add(&self.alarms, 1);
    }

    /// The link came up (a new session with the device).
    pub fn session(&self) {
        add(&self.sessions, 1);
    }

    /// A DO command reached the host engine `delay` after it was asked for: from the put's
    /// zenoh timestamp (the client's clock) or, without one, its arrival at the gateway. The
    /// wait for the board's next SAT or GTD (§4.4.1) comes after and is not in it.
    pub fn do_delay(&self, delay: Duration) {
        for (_, h) in lock(&registry().histograms).iter() {
            h.do_delay.record(delay.as_secs_f64(), &self.attrs);
        }
    }

    /// Bytes received and sent so far (for tests and status).
    pub fn bytes(&self) -> (u64, u64) {
        (self.bytes_in.load(Relaxed), self.bytes_out.load(Relaxed))
    }

    /// Every counter now.
    pub fn counts(&self) -> LinkCounts {
        LinkCounts {
            bytes_in: self.bytes_in.load(Relaxed),
            bytes_out: self.bytes_out.load(Relaxed),
            frames_in: self.frames_in.load(Relaxed),
            frames_out: self.frames_out.load(Relaxed),
            retries: self.retries.load(Relaxed),
            checksum_errors: self.checksum_errors.load(Relaxed),
            line_errors: self.line_errors.load(Relaxed),
            alarms: self.alarms.load(Relaxed),
            sessions: self.sessions.load(Relaxed),
        }
    }
}

/// A link's counters at one moment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LinkCounts {
    pub bytes_in: u64,
    pub bytes_out: u64,
    pub frames_in: u64,
    pub frames_out: u64,
    pub retries: u64,
    pub checksum_errors: u64,
    pub line_errors: u64,
    pub alarms: u64,
    pub sessions: u64,
}

/// How a job ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    Completed,
    Failed,
    Cancelled,
}

impl Outcome {
    pub fn as_str(self) -> &'static str {
        match self {
            Outcome::Completed => "completed",
            Outcome::Failed => "failed",
            Outcome::Cancelled => "cancelled",
        }
    }

    const ALL: [Outcome; 3] = [Outcome::Completed, Outcome::Failed, Outcome::Cancelled];
}

/// One machine's job and G05 counters.
#[derive(Debug)]
pub struct MachineMetrics {
    name: Arc<str>,
    attrs: [KeyValue; 1],
    /// Per outcome: the machine, then the outcome; built once, borrowed at every record.
    outcome_attrs: [[KeyValue; 2]; 3],
    queue_depth: AtomicU64,
    ended: [AtomicU64; 3],
    g05_underruns: AtomicU64,
}

impl MachineMetrics {
    fn new(name: &str) -> Self {
        let machine = KeyValue::new("machine", name.to_string());
        let outcome_attrs =
            Outcome::ALL.map(|o| [machine.clone(), KeyValue::new("outcome", o.as_str())]);
        MachineMetrics {
            name: Arc::from(name),
            attrs: [machine],
            outcome_attrs,
            queue_depth: AtomicU64::new(0),
            ended: Default::default(),
            g05_underruns: AtomicU64::new(0),
        }
    }

    /// Jobs waiting now (not counting the one being sent).
    pub fn set_queue_depth(&self, waiting: usize) {
        self.queue_depth
            .store(u64::try_from(waiting).unwrap_or(u64::MAX), Relaxed);
    }

    /// A job ended; `sending` is how long it was on the link, if it got there.
    pub fn job_ended(&self, outcome: Outcome, sending: Option<Duration>) {
        add(&self.ended[outcome as usize], 1);
        if let Some(d) = sending {
            let attrs = &self.outcome_attrs[outcome as usize];
            for (_, h) in lock(&registry().histograms).iter() {
                h.job_duration.record(d.as_secs_f64(), attrs);
            }
        }
    }

    /// Slots the CNC found no G05 block for (estimated, §9.2).
    pub fn add_g05_underruns(&self, n: u64) {
        add(&self.g05_underruns, n);
    }

    /// Jobs ended so far with `outcome`.
    pub fn ended(&self, outcome: Outcome) -> u64 {
        self.ended[outcome as usize].load(Relaxed)
    }

    pub fn name(&self) -> &str {
        &self.name
    }
}

/// The synchronous instruments of one meter provider.
#[derive(Debug)]
struct Histograms {
    job_duration: Histogram<f64>,
    do_delay: Histogram<f64>,
}

/// A rare event's name and attributes.
type EventKey = (&'static str, Vec<(&'static str, String)>);

#[derive(Debug, Default)]
struct Registry {
    links: Mutex<BTreeMap<String, Arc<LinkMetrics>>>,
    machines: Mutex<BTreeMap<String, Arc<MachineMetrics>>>,
    /// (PLC, station) → time-outs.
    plc_timeouts: Mutex<BTreeMap<(String, u8), u64>>,
    /// Rare events ([`EVENTS`]) by name and attributes.
    events: Mutex<BTreeMap<EventKey, u64>>,
    /// (cell, log) → records the historian has yet to copy.
    historian_lag: Mutex<BTreeMap<(String, &'static str), u64>>,
    /// The histograms of every installed provider, by install number.
    histograms: Mutex<Vec<(u64, Histograms)>>,
    installs: AtomicU64,
}

fn registry() -> &'static Registry {
    static REGISTRY: OnceLock<Registry> = OnceLock::new();
    REGISTRY.get_or_init(Registry::default)
}

/// A poisoned lock still holds counters worth reading: a panic elsewhere must not stop
/// metrics (the SDK does not survive a panicking callback).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

fn add(counter: &AtomicU64, n: u64) {
    if n > 0 {
        counter.fetch_add(n, Relaxed);
    }
}

/// The counters of link `name`, the same ones every time for the same name.
pub fn link(name: &str) -> Arc<LinkMetrics> {
    let mut links = lock(&registry().links);
    Arc::clone(
        links
            .entry(name.to_string())
            .or_insert_with(|| Arc::new(LinkMetrics::new(name))),
    )
}

/// The counters of machine `name`, the same ones every time for the same name.
pub fn machine(name: &str) -> Arc<MachineMetrics> {
    let mut machines = lock(&registry().machines);
    Arc::clone(
        machines
            .entry(name.to_string())
            .or_insert_with(|| Arc::new(MachineMetrics::new(name))),
    )
}

/// A PLC station did not answer in time. The hook the PLC link calls; rare enough for a
/// lock and a map lookup.
pub fn plc_station_timeout(plc: &str, station: u8) {
    *lock(&registry().plc_timeouts)
        .entry((plc.to_string(), station))
        .or_insert(0) += 1;
}

/// Time-outs of PLC `plc`'s station `station` so far.
pub fn plc_station_timeouts(plc: &str, station: u8) -> u64 {
    lock(&registry().plc_timeouts)
        .get(&(plc.to_string(), station))
        .copied()
        .unwrap_or(0)
}

/// The counters of rare events [`event`] counts, with their descriptions.
pub const EVENTS: [(&str, &str); 6] = [
    (
        "cellgate.bus.misdirected_writes",
        "Puts and deletes on keys that only read: nothing was written",
    ),
    (
        "cellgate.history.dropped",
        "History and audit records dropped before their retention days",
    ),
    (
        "cellgate.console.login_failures",
        "Console logins refused (wrong name or password) or throttled",
    ),
    (
        "cellgate.listen.refused",
        "Connections closed at once: their listener held as many as it may",
    ),
    (
        "cellgate.historian.records",
        "Records the historian copied into the database",
    ),
    (
        "cellgate.historian.failures",
        "Copies the historian tried and could not make (the database or a gateway away)",
    ),
];

/// The historian's lag of `cell`'s `log`: records its gateway holds that the database does
/// not yet.
pub fn historian_lag(cell: &str, log: &'static str, lag: u64) {
    lock(&registry().historian_lag).insert((cell.to_string(), log), lag);
}

/// Counts `n` rare events of counter `name` (one of [`EVENTS`]) with `attrs`: a lock and
/// a map lookup, for what happens now and then, not per byte.
pub fn event(name: &'static str, attrs: &[(&'static str, &str)], n: u64) {
    let key = (
        name,
        attrs.iter().map(|(k, v)| (*k, (*v).to_string())).collect(),
    );
    *lock(&registry().events).entry(key).or_insert(0) += n;
}

/// Events of counter `name` with `attrs` so far.
pub fn events(name: &'static str, attrs: &[(&'static str, &str)]) -> u64 {
    let key = (
        name,
        attrs.iter().map(|(k, v)| (*k, (*v).to_string())).collect(),
    );
    lock(&registry().events).get(&key).copied().unwrap_or(0)
}

/// Instruments registered on one meter provider; dropping it stops recording job durations
/// and DO delays into that provider.
#[derive(Debug)]
pub struct Instruments {
    install: u64,
}

impl Drop for Instruments {
    fn drop(&mut self) {
        lock(&registry().histograms).retain(|(n, _)| *n != self.install);
    }
}

/// Registers every instrument of the table above on `provider`. Observable instruments live
/// as long as the provider's pipeline: their handles are not kept.
pub fn register(provider: &SdkMeterProvider) -> Instruments {
    let meter = provider.meter(SCOPE);
    register_links(&meter);
    register_machines(&meter);
    for (name, description) in EVENTS {
        let _ = meter
            .u64_observable_counter(name)
            .with_description(description)
            .with_callback(move |o| {
                for ((n, attrs), v) in lock(&registry().events).iter() {
                    if *n == name {
                        let attrs: Vec<KeyValue> = attrs
                            .iter()
                            .map(|(k, v)| KeyValue::new(*k, v.clone()))
                            .collect();
                        o.observe(*v, &attrs);
                    }
                }
            })
            .build();
    }
    let _ = meter
        .u64_observable_counter("cellgate.plc.station_timeouts")
        .with_description("PLC stations that did not answer within the time-out")
        .with_callback(|o| {
            for ((plc, station), n) in lock(&registry().plc_timeouts).iter() {
                o.observe(
                    *n,
                    &[
                        KeyValue::new("plc", plc.clone()),
                        KeyValue::new("station", i64::from(*station)),
                    ],
                );
            }
        })
        .build();
    let _ = meter
        .u64_observable_gauge("cellgate.historian.lag")
        .with_description("Records a cell's gateway holds that the historian has not copied yet")
        .with_callback(|o| {
            for ((cell, log), n) in lock(&registry().historian_lag).iter() {
                o.observe(
                    *n,
                    &[
                        KeyValue::new("cell", cell.clone()),
                        KeyValue::new("log", *log),
                    ],
                );
            }
        })
        .build();
    let durations = meter
        .f64_histogram("cellgate.job.duration")
        .with_unit("s")
        .with_description("How long jobs were on the link, from start to end")
        .with_boundaries(vec![
            0.1, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0,
        ])
        .build();
    let do_delay = meter
        .f64_histogram("cellgate.do.delay")
        .with_unit("s")
        .with_description(
            "From a DO command's put (its timestamp, else its arrival) to the host engine",
        )
        // Fine at the low end: the gateway's own share is milliseconds at most.
        .with_boundaries(vec![
            0.0005, 0.001, 0.002, 0.003, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 5.0,
        ])
        .build();
    let r = registry();
    let install = r.installs.fetch_add(1, Relaxed);
    lock(&r.histograms).push((
        install,
        Histograms {
            job_duration: durations,
            do_delay,
        },
    ));
    Instruments { install }
}

fn register_links(meter: &Meter) {
    type Pick = fn(&LinkMetrics) -> u64;
    let directed: [(&'static str, &'static str, Option<&'static str>, Pick, Pick); 2] = [
        (
            "cellgate.link.io",
            "Bytes read from (in) and written to (out) the line",
            Some("By"),
            |l| l.bytes_in.load(Relaxed),
            |l| l.bytes_out.load(Relaxed),
        ),
        (
            "cellgate.link.frames",
            "Protocol frames received (in) and sent (out): messages, packets, control codes",
            None,
            |l| l.frames_in.load(Relaxed),
            |l| l.frames_out.load(Relaxed),
        ),
    ];
    for (name, description, unit, pick_in, pick_out) in directed {
        let mut b = meter
            .u64_observable_counter(name)
            .with_description(description)
            .with_callback(move |o| {
                for l in lock(&registry().links).values() {
                    let link = l.attrs[0].clone();
                    o.observe(
                        pick_in(l),
                        &[link.clone(), KeyValue::new("direction", "in")],
                    );
                    o.observe(pick_out(l), &[link, KeyValue::new("direction", "out")]);
                }
            });
        if let Some(unit) = unit {
            b = b.with_unit(unit);
        }
        let _ = b.build();
    }
    let plain: [(&'static str, &'static str, Pick); 5] = [
        (
            "cellgate.link.retries",
            "Messages sent again (RTY received or sent)",
            |l| l.retries.load(Relaxed),
        ),
        (
            "cellgate.link.checksum_errors",
            "Received frames with a bad checksum",
            |l| l.checksum_errors.load(Relaxed),
        ),
        (
            "cellgate.link.line_errors",
            "Character errors on the line: parity, framing, overrun",
            |l| l.line_errors.load(Relaxed),
        ),
        ("cellgate.link.alarms", "Link alarms", |l| {
            l.alarms.load(Relaxed)
        }),
        (
            "cellgate.link.sessions",
            "Times the link came up with its device",
            |l| l.sessions.load(Relaxed),
        ),
    ];
    for (name, description, pick) in plain {
        let _ = meter
            .u64_observable_counter(name)
            .with_description(description)
            .with_callback(move |o| {
                for l in lock(&registry().links).values() {
                    o.observe(pick(l), &l.attrs);
                }
            })
            .build();
    }
}

fn register_machines(meter: &Meter) {
    let _ = meter
        .u64_observable_gauge("cellgate.jobs.queue_depth")
        .with_description("Jobs waiting for the machine's link (not counting the one sent)")
        .with_callback(|o| {
            for m in lock(&registry().machines).values() {
                o.observe(m.queue_depth.load(Relaxed), &m.attrs);
            }
        })
        .build();
    let _ = meter
        .u64_observable_counter("cellgate.jobs.ended")
        .with_description("Jobs ended, by outcome")
        .with_callback(|o| {
            for m in lock(&registry().machines).values() {
                for outcome in Outcome::ALL {
                    o.observe(
                        m.ended[outcome as usize].load(Relaxed),
                        &m.outcome_attrs[outcome as usize],
                    );
                }
            }
        })
        .build();
    let _ = meter
        .u64_observable_counter("cellgate.g05.underruns")
        .with_description("G05 unit-time slots the CNC found no block for (estimated)")
        .with_callback(|o| {
            for m in lock(&registry().machines).values() {
                o.observe(m.g05_underruns.load(Relaxed), &m.attrs);
            }
        })
        .build();
}

#[cfg(test)]
mod tests;
