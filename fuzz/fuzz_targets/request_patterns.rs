//! Arbitrary remote request patterns and arbitrary punched text: parsing and matching never
//! panic, and a request found names a program number of digits.
#![no_main]

use cellgate_core::program::punch::{PunchedText, RequestPatterns};
use cellgate_core::program::tape::TapeCode;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let split = data.iter().position(|&b| b == 0).unwrap_or(data.len());
    let (pattern_bytes, text) = data.split_at(split);
    let patterns: Vec<String> = String::from_utf8_lossy(pattern_bytes)
        .split('\n')
        .map(str::to_string)
        .collect();
    let patterns = RequestPatterns::parse(&patterns).unwrap_or_else(|_| {
        RequestPatterns::parse(&["(REQ O{n})".to_string()]).expect("the default parses")
    });
    let program = PunchedText {
        text: text.to_vec(),
        code: TapeCode::Iso,
        o_number: None,
        comment: None,
        damage: None,
    };
    if let Some(request) = patterns.match_program(&program) {
        assert!(request.program.starts_with('O'));
        assert!(request.program[1..].bytes().all(|b| b.is_ascii_digit()));
        assert!(!request.candidates().is_empty());
    }
});
