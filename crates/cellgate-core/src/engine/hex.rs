//! Upper-case hexadecimal digits, as both manuals write numbers on the line: the FANUC
//! remote buffer's messages and SAT fields (protocol notes 1), the FFU120B's BCC and
//! addresses (FFU120B §4-3 item 14: "0 to 9, A to F").

/// The sixteen digits, by value.
pub const DIGITS: &[u8; 16] = b"0123456789ABCDEF";

/// The two hex digits of `v`, high first.
pub fn hex2(v: u8) -> [u8; 2] {
    [DIGITS[usize::from(v >> 4)], DIGITS[usize::from(v & 0xF)]]
}
