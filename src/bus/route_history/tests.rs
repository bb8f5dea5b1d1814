use super::*;
use std::time::{Duration, UNIX_EPOCH};

#[test]
fn time_ranges_read_as_zenoh_reads_them() {
    let now = UNIX_EPOCH + Duration::from_secs(1_800_000_000);
    let ms = 1_800_000_000_000u64;
    assert_eq!(
        time_range("[now(-1h)..]", now).unwrap(),
        (ms - 3_600_000, ms)
    );
    assert_eq!(
        time_range("[..now(-1d)]", now).unwrap(),
        (0, ms - 86_400_000)
    );
    assert_eq!(
        time_range("]2026-12-01T00:00:00Z..2026-12-01T01:00:00Z[", now).unwrap(),
        (1_796_083_200_001, 1_796_086_799_999)
    );
    assert_eq!(
        time_range("[2026-12-01T00:00:00Z;30m]", now).unwrap(),
        (1_796_083_200_000, 1_796_085_000_000)
    );
    assert!(time_range("yesterday", now).is_err());
    assert!(time_range("[now(-1x)..]", now).is_err());
}
