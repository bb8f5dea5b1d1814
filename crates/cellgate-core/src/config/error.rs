//! Every error of a cell file, collected at once by a [`Checker`], each naming its key path,
//! the value, what is allowed and the manual section.

use std::fmt::{self, Write as _};

use serde::Serialize;

use crate::fanuc::sat::ParamRangeError;

/// One thing wrong with a cell file.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{origin}: cannot read the cell file: {reason}")]
    Read {
        /// The file's path.
        origin: String,
        /// The I/O error, as text.
        reason: String,
    },
    /// A key the cell file does not have, with the known key it most likely means.
    #[error("{origin}:{line}: unknown key `{key}`{}; this table takes {expected}", suggestion.as_ref().map(|s| format!(" (did you mean `{s}`?)")).unwrap_or_default())]
    Unknown {
        /// The file's path.
        origin: String,
        /// The line of the key, counting from 1.
        line: usize,
        /// The key as written.
        key: String,
        /// The known key closest to it, if one is close.
        suggestion: Option<String>,
        /// The keys the table takes, as the parser lists them.
        expected: String,
    },
    /// TOML syntax, an unknown key or a value of the wrong type; `message` is the toml
    /// crate's, which names the line and the key.
    #[error("{origin}: {message}")]
    Parse {
        /// The file's name: the path it was read from, or the name the caller gave.
        origin: String,
        /// The toml crate's message, naming the line and the key.
        message: String,
    },
    /// A required key is absent.
    #[error("{path}: missing; {hint}")]
    Missing {
        /// The key path of the absent key, e.g. `machines[2].name`.
        path: String,
        /// What the key is for or should hold.
        hint: String,
    },
    /// A §4.5 remote-buffer parameter outside its range; `path` is the machine's
    /// (`machines.mill-1`), `range` names the parameter.
    #[error("{path}.{range}")]
    Param {
        /// The machine's path, e.g. `machines.mill-1`.
        path: String,
        /// The parameter, the value given and the range allowed.
        range: ParamRangeError,
    },
    /// A value that is not allowed, alone or with the other settings.
    #[error("{path} = {value}: {reason}{}", cite(.section))]
    Invalid {
        /// The key path, e.g. `machines.mill-1.tp`.
        path: String,
        /// The value given, as text.
        value: String,
        /// Why it is not allowed, and what is.
        reason: String,
        /// The manual section to cite (e.g. `§4.5`); empty when there is none.
        section: &'static str,
    },
    /// A key that has no meaning with the other settings (e.g. an end code for Protocol B).
    #[error("{path}: {reason}{}", cite(.section))]
    NotApplicable {
        /// The key path of the key that does not apply, e.g. `machines.mill-1.sim`.
        path: String,
        /// Why it has no meaning with the other settings.
        reason: String,
        /// The manual section to cite; empty when there is none.
        section: &'static str,
    },
    /// A setting the host engine itself refuses, in a way the rules above do not name.
    #[error("{path}: {problem}")]
    ProtocolA {
        /// The machine's path, e.g. `machines.mill-1`.
        path: String,
        /// What the Protocol A engine refuses.
        problem: crate::fanuc::protocol_a::ProtocolAProblem,
    },
    /// A setting the Protocol B host engine itself refuses.
    #[error("{path}: {problem}")]
    ProtocolB {
        /// The machine's path, e.g. `machines.mill-1`.
        path: String,
        /// What the Protocol B engine refuses.
        problem: crate::fanuc::protocol_b::ProtocolBProblem,
    },
    /// A file the cell file names (a certificate, a key, a user list) that is missing,
    /// unreadable or not what it should be. Never carries the file's content.
    #[error("{path} = {}: {problem}", file.display())]
    File {
        /// The key that names the file, e.g. `security.users_file`.
        path: String,
        /// The file's path.
        file: std::path::PathBuf,
        /// What is wrong with the file.
        problem: String,
    },
    /// A role names a permission that does not exist.
    #[error("{path}: unknown permission {name:?}; the permissions are: {known}")]
    UnknownPermission {
        /// The key path of the role's permissions, e.g. `security.roles[1].permissions[2]`.
        path: String,
        /// The permission name given.
        name: String,
        /// The names of every permission, comma-separated.
        known: String,
    },
    /// Two links with the same name.
    #[error(
        "{path}: {first} and {second} are both named {name:?}; names must be unique in a cell \
         (each becomes a key chunk)"
    )]
    Duplicate {
        /// The path the name gives, `table.name` (e.g. `machines.mill-1`).
        path: String,
        /// The name both links have.
        name: String,
        /// The first link's position, e.g. `[[machines]] #1`.
        first: String,
        /// The second link's position.
        second: String,
    },
}

pub(super) fn cite(section: &str) -> String {
    if section.is_empty() {
        String::new()
    } else {
        format!(" ({section})")
    }
}

impl ConfigError {
    /// The key path the error is about (`machines.mill-1.tw`), if it is about one.
    pub fn path(&self) -> Option<String> {
        match self {
            ConfigError::Read { .. } | ConfigError::Parse { .. } => None,
            ConfigError::Unknown { key, .. } => Some(key.clone()),
            ConfigError::Param { path, range } => Some(format!("{path}.{}", range.name)),
            ConfigError::Missing { path, .. }
            | ConfigError::Invalid { path, .. }
            | ConfigError::NotApplicable { path, .. }
            | ConfigError::ProtocolA { path, .. }
            | ConfigError::ProtocolB { path, .. }
            | ConfigError::Duplicate { path, .. }
            | ConfigError::File { path, .. }
            | ConfigError::UnknownPermission { path, .. } => Some(path.clone()),
        }
    }
}

/// Every error found in a cell file. Displays one error per line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfigErrors(pub Vec<ConfigError>);

impl ConfigErrors {
    /// The number of errors.
    pub fn len(&self) -> usize {
        self.0.len()
    }
    /// Whether there are no errors.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
    /// Iterates over the errors, in the order they were found.
    pub fn iter(&self) -> std::slice::Iter<'_, ConfigError> {
        self.0.iter()
    }
}

impl fmt::Display for ConfigErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, e) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_char('\n')?;
            }
            write!(f, "{e}")?;
        }
        Ok(())
    }
}

impl std::error::Error for ConfigErrors {}

impl From<ConfigError> for ConfigErrors {
    fn from(e: ConfigError) -> Self {
        ConfigErrors(vec![e])
    }
}

impl<'a> IntoIterator for &'a ConfigErrors {
    type Item = &'a ConfigError;
    type IntoIter = std::slice::Iter<'a, ConfigError>;
    fn into_iter(self) -> Self::IntoIter {
        self.0.iter()
    }
}

pub(super) struct Checker {
    pub(super) errors: Vec<ConfigError>,
    /// Whether files the cell file names (certificates, keys, the users file) are read and
    /// checked; off for what needs only the file's own settings (`cellgate acl`).
    pub(super) files: bool,
}

impl Checker {
    pub(super) fn invalid(
        &mut self,
        path: String,
        value: String,
        reason: String,
        section: &'static str,
    ) {
        self.errors.push(ConfigError::Invalid {
            path,
            value,
            reason,
            section,
        });
    }

    pub(super) fn not_applicable(&mut self, path: String, reason: String, section: &'static str) {
        self.errors.push(ConfigError::NotApplicable {
            path,
            reason,
            section,
        });
    }

    pub(super) fn missing(&mut self, path: String, hint: &str) {
        self.errors.push(ConfigError::Missing {
            path,
            hint: hint.to_string(),
        });
    }

    /// `value` within `min..=max`, else an error stating the range and `why`.
    pub(super) fn range<T: PartialOrd + fmt::Display>(
        &mut self,
        path: impl FnOnce() -> String,
        value: T,
        min: T,
        max: T,
        why: &str,
        section: &'static str,
    ) {
        if value < min || value > max {
            self.invalid(
                path(),
                value.to_string(),
                format!("must be within {min}..={max}{why}"),
                section,
            );
        }
    }
}

pub(super) fn list_u32(v: &[u32]) -> String {
    let s: Vec<String> = v.iter().map(u32::to_string).collect();
    s.join(", ")
}

pub(super) fn q(s: &str) -> String {
    format!("{s:?}")
}

/// The serde name of a unit enum value, quoted as in the file (`"expansion-a"`).
pub(super) fn toml_name<T: Serialize>(v: &T) -> String {
    q(&plain_name(v))
}

/// The name of a unit enum value as the file spells it, without quotes.
pub(super) fn plain_name<T: Serialize>(v: &T) -> String {
    match toml::Value::try_from(v) {
        Ok(toml::Value::String(s)) => s,
        Ok(other) => other.to_string(),
        Err(_) => "?".to_string(),
    }
}
