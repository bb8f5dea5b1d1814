//! Program names: one key chunk of `P/C/program/<name>` and a plain file name at once, so a
//! name rules out path traversal (`..`, `/`), hidden files, and every zenoh wildcard or
//! reserved character: 1 to 128 characters of `A-Z a-z 0-9 . _ + -`, starting with a letter
//! or a digit.

/// Longest program number: O and up to 8 digits, in a program's text and in a name made of it.
pub const O_DIGITS_MAX: usize = 8;

/// Longest program name.
pub const NAME_MAX: usize = 128;

/// Why a name is not a program name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("program name {name:?} is not valid: {reason}")]
pub struct NameError {
    /// The name as given.
    pub name: String,
    /// What is wrong with it.
    pub reason: &'static str,
}

/// Checks a program name (see the module documentation).
pub fn check_name(name: &str) -> Result<(), NameError> {
    let invalid = |reason| {
        Err(NameError {
            name: name.to_string(),
            reason,
        })
    };
    if name.is_empty() {
        return invalid("it is empty");
    }
    if name.len() > NAME_MAX {
        return invalid("it is longer than 128 characters");
    }
    if !name
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || b"._+-".contains(&b))
    {
        return invalid("use only letters, digits, '.', '_', '+' and '-'");
    }
    if !name
        .as_bytes()
        .first()
        .is_some_and(u8::is_ascii_alphanumeric)
    {
        return invalid("it must start with a letter or a digit");
    }
    Ok(())
}
