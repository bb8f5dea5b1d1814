//! Arbitrary text as a cell file: reading never panics; a file that reads validates, writes
//! out, and reads back the same.
#![no_main]

use cellgate_core::config::CellConfig;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(cell) = CellConfig::from_toml_str(text, "fuzz") else {
        return;
    };
    cell.validate().expect("a cell file that reads validates");
    let _ = cell.summary();
    let written = cell.to_toml_string().expect("a valid cell writes out");
    let again = CellConfig::from_toml_str(&written, "fuzz again").expect("and reads back");
    assert_eq!(again, cell);
});
