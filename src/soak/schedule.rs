//! The fault schedule: drawn from a seed, so that a run that found something can be run again
//! the same way. Every kind comes once a round, in a shuffled order, so that a long run injects
//! each about as often as the others.

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// What goes wrong.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum FaultKind {
    /// A line's connection closed mid-exchange.
    LineCut,
    /// A board process killed (every board of a protocol loses power) and started again.
    DeviceServerRestart,
    /// A byte with a flipped bit in the host's next write (A family: NAK and resend).
    ChecksumError,
    /// A byte missing from the host's next write (A family).
    DroppedByte,
    /// A CNC alarm raised by the operator, reset a few seconds later.
    CncAlarm,
    /// A CNC reset by the operator (buffered data lost, §8.2).
    CncReset,
    /// `kill -9` of the gateway, started again two seconds later.
    GatewayKill,
    /// The cell file changed: the spare machine added, removed or its Tp changed.
    Reload,
    /// The router between the clients and the gateway killed and started again.
    RouterRestart,
    /// The gateway's data filesystem full for fifteen seconds.
    DiskFull,
    /// A subscriber to every key of the cell that reads nothing for twenty seconds.
    SlowSubscriber,
    /// A burst of hostile requests: garbage payloads, wrong keys, oversized bodies.
    HostileBurst,
}

impl FaultKind {
    pub(crate) const ALL: [FaultKind; 12] = [
        FaultKind::LineCut,
        FaultKind::DeviceServerRestart,
        FaultKind::ChecksumError,
        FaultKind::DroppedByte,
        FaultKind::CncAlarm,
        FaultKind::CncReset,
        FaultKind::GatewayKill,
        FaultKind::Reload,
        FaultKind::RouterRestart,
        FaultKind::DiskFull,
        FaultKind::SlowSubscriber,
        FaultKind::HostileBurst,
    ];

    pub(crate) fn name(self) -> &'static str {
        match self {
            FaultKind::LineCut => "line-cut",
            FaultKind::DeviceServerRestart => "device-server-restart",
            FaultKind::ChecksumError => "checksum-error",
            FaultKind::DroppedByte => "dropped-byte",
            FaultKind::CncAlarm => "cnc-alarm",
            FaultKind::CncReset => "cnc-reset",
            FaultKind::GatewayKill => "gateway-kill",
            FaultKind::Reload => "reload",
            FaultKind::RouterRestart => "router-restart",
            FaultKind::DiskFull => "disk-full",
            FaultKind::SlowSubscriber => "slow-subscriber",
            FaultKind::HostileBurst => "hostile-burst",
        }
    }
}

/// `--faults`: a kind by its name.
pub fn parse_kind(text: &str) -> Result<FaultKind, String> {
    FaultKind::ALL
        .into_iter()
        .find(|k| k.name() == text.trim())
        .ok_or_else(|| {
            let names: Vec<&str> = FaultKind::ALL.iter().map(|k| k.name()).collect();
            format!("{text:?} is no fault kind; the kinds: {}", names.join(", "))
        })
}

/// One fault: when, what, and a number that picks its target (a machine, a protocol).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Fault {
    pub(crate) at_s: f64,
    pub(crate) kind: FaultKind,
    pub(crate) pick: u32,
}

/// Faults from `start_s` to `end_s`, one about every `every_s` (±30 %), each round of
/// `kinds` in a shuffled order.
pub(crate) fn schedule(
    seed: u64,
    start_s: f64,
    end_s: f64,
    every_s: f64,
    kinds: &[FaultKind],
) -> Vec<Fault> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = Vec::new();
    if kinds.is_empty() || every_s <= 0.0 || !every_s.is_finite() {
        return out;
    }
    let mut t = start_s;
    let mut round: Vec<FaultKind> = Vec::new();
    loop {
        t += every_s * rng.random_range(0.7..1.3);
        if t >= end_s {
            return out;
        }
        if round.is_empty() {
            round = kinds.to_vec();
            round.shuffle(&mut rng);
        }
        if let Some(kind) = round.pop() {
            out.push(Fault {
                at_s: t,
                kind,
                pick: rng.random(),
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_same_seed_gives_the_same_schedule_and_another_seed_another() {
        let a = schedule(7, 10.0, 600.0, 5.0, &FaultKind::ALL);
        let b = schedule(7, 10.0, 600.0, 5.0, &FaultKind::ALL);
        let c = schedule(8, 10.0, 600.0, 5.0, &FaultKind::ALL);
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn every_kind_comes_once_a_round_within_the_run() {
        let s = schedule(1, 30.0, 3600.0, 25.0, &FaultKind::ALL);
        assert!(s.iter().all(|f| f.at_s > 30.0 && f.at_s < 3600.0));
        assert!(s.windows(2).all(|w| w[0].at_s < w[1].at_s));
        for round in s.chunks_exact(FaultKind::ALL.len()) {
            let mut kinds: Vec<FaultKind> = round.iter().map(|f| f.kind).collect();
            kinds.sort();
            assert_eq!(kinds, FaultKind::ALL);
        }
        // An hour at one every 25 s: more than ten of each kind.
        for k in FaultKind::ALL {
            assert!(s.iter().filter(|f| f.kind == k).count() >= 10, "{k:?}");
        }
    }

    #[test]
    fn no_kinds_or_no_time_give_no_faults() {
        assert!(schedule(1, 0.0, 100.0, 5.0, &[]).is_empty());
        assert!(schedule(1, 100.0, 50.0, 5.0, &FaultKind::ALL).is_empty());
        assert!(schedule(1, 0.0, 100.0, 0.0, &FaultKind::ALL).is_empty());
    }
}
