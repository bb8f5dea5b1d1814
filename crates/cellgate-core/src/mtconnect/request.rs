//! What a request asks (MTConnect Part 1, "REST API"): its query parameters, checked, and its
//! errors with the standard's codes.

use std::fmt;

/// The error codes of an MTConnectError document (the 2.5 schema's `ErrorCodeEnum`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorCode {
    /// The device in the URI is not here.
    NoDevice,
    /// A sequence number or count outside the buffer.
    OutOfRange,
    /// A count too large.
    TooMany,
    /// A URI the agent does not serve.
    InvalidUri,
    /// A request it does not know, or a parameter it cannot read.
    InvalidRequest,
    /// The agent failed.
    InternalError,
    /// A `path` the agent cannot read, or that selects nothing.
    InvalidPath,
    /// Something the agent does not do (a write: it only reads).
    Unsupported,
    /// No asset with that id.
    AssetNotFound,
}

impl ErrorCode {
    /// The code as the document gives it.
    pub fn name(self) -> &'static str {
        match self {
            ErrorCode::NoDevice => "NO_DEVICE",
            ErrorCode::OutOfRange => "OUT_OF_RANGE",
            ErrorCode::TooMany => "TOO_MANY",
            ErrorCode::InvalidUri => "INVALID_URI",
            ErrorCode::InvalidRequest => "INVALID_REQUEST",
            ErrorCode::InternalError => "INTERNAL_ERROR",
            ErrorCode::InvalidPath => "INVALID_PATH",
            ErrorCode::Unsupported => "UNSUPPORTED",
            ErrorCode::AssetNotFound => "ASSET_NOT_FOUND",
        }
    }

    /// The HTTP status it goes with.
    pub fn http_status(self) -> u16 {
        match self {
            ErrorCode::NoDevice | ErrorCode::InvalidUri | ErrorCode::AssetNotFound => 404,
            ErrorCode::InternalError => 500,
            ErrorCode::Unsupported => 405,
            _ => 400,
        }
    }
}

/// A request the agent refuses, as an MTConnectError document says it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{}: {message}", code.name())]
pub struct MtError {
    /// The code.
    pub code: ErrorCode,
    /// What was wrong, for people.
    pub message: String,
}

impl MtError {
    /// An error of `code`.
    pub fn new(code: ErrorCode, message: impl Into<String>) -> MtError {
        MtError {
            code,
            message: message.into(),
        }
    }
}

impl From<super::buffer::OutOfRange> for MtError {
    fn from(e: super::buffer::OutOfRange) -> Self {
        MtError::new(ErrorCode::OutOfRange, e.to_string())
    }
}

/// A document's format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Format {
    /// `text/xml`.
    #[default]
    Xml,
    /// `application/json`.
    Json,
}

/// The query parameters of a request, read and checked for their form.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Query {
    /// `path`: which data items.
    pub path: Option<String>,
    /// `at`: `/current` as of this sequence number.
    pub at: Option<i64>,
    /// `from`: `/sample` from this sequence number.
    pub from: Option<i64>,
    /// `count`: observations at most (default 100).
    pub count: Option<i64>,
    /// `interval`: stream, at most one part per this many ms.
    pub interval: Option<u64>,
    /// `heartbeat`: ms without data before an empty part (default 10 000).
    pub heartbeat: Option<u64>,
    /// `format`: xml or json.
    pub format: Format,
    /// `type`, `removed` (assets).
    pub asset_type: Option<String>,
    /// `pretty=true`: the document laid out for reading ([`super::pretty`]).
    pub pretty: bool,
}

/// What each request takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request {
    /// `/probe`.
    Probe,
    /// `/current`.
    Current,
    /// `/sample`.
    Sample,
    /// `/assets`, `/asset/ID`.
    Assets,
}

impl fmt::Display for Request {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Request::Probe => "probe",
            Request::Current => "current",
            Request::Sample => "sample",
            Request::Assets => "assets",
        })
    }
}

fn int(name: &str, v: &str) -> Result<i64, MtError> {
    v.trim().parse::<i64>().map_err(|_| {
        MtError::new(
            ErrorCode::InvalidRequest,
            format!("query parameter '{name}' must be an integer, not {v:?}"),
        )
    })
}

fn ms(name: &str, v: &str, min: i64) -> Result<u64, MtError> {
    let n = int(name, v)?;
    if n < min || n > i64::from(i32::MAX) {
        return Err(MtError::new(
            ErrorCode::OutOfRange,
            format!(
                "'{name}' must be between {min} and {}; {n} is not",
                i32::MAX
            ),
        ));
    }
    Ok(n as u64)
}

impl Query {
    /// Reads the query pairs of `request`; a parameter it does not take, or one given twice,
    /// is an INVALID_REQUEST.
    pub fn parse<'a>(
        request: Request,
        pairs: impl IntoIterator<Item = (&'a str, &'a str)>,
    ) -> Result<Query, MtError> {
        let allowed: &[&str] = match request {
            Request::Probe => &["format", "pretty"],
            Request::Current => &["path", "at", "interval", "format", "pretty"],
            Request::Sample => &[
                "path",
                "from",
                "count",
                "interval",
                "heartbeat",
                "format",
                "pretty",
            ],
            Request::Assets => &["type", "count", "removed", "format", "pretty", "device"],
        };
        let mut q = Query::default();
        let mut seen: Vec<&str> = Vec::new();
        for (k, v) in pairs {
            if !allowed.contains(&k) {
                return Err(MtError::new(
                    ErrorCode::InvalidRequest,
                    format!(
                        "{request} takes no query parameter {k:?}; it takes {}",
                        allowed.join(", ")
                    ),
                ));
            }
            if seen.contains(&k) {
                return Err(MtError::new(
                    ErrorCode::InvalidRequest,
                    format!("query parameter {k:?} is given twice"),
                ));
            }
            seen.push(k);
            match k {
                "path" => q.path = Some(v.to_string()),
                "at" => q.at = Some(int(k, v)?),
                "from" => q.from = Some(int(k, v)?),
                "count" => q.count = Some(int(k, v)?),
                "interval" => q.interval = Some(ms(k, v, 0)?),
                "heartbeat" => q.heartbeat = Some(ms(k, v, 1)?),
                "type" => q.asset_type = Some(v.to_string()),
                "format" => {
                    q.format = match v.to_ascii_lowercase().as_str() {
                        "xml" => Format::Xml,
                        "json" => Format::Json,
                        _ => {
                            return Err(MtError::new(
                                ErrorCode::InvalidRequest,
                                format!("format must be xml or json, not {v:?}"),
                            ));
                        }
                    }
                }
                "pretty" => {
                    q.pretty = match v.to_ascii_lowercase().as_str() {
                        "true" => true,
                        "false" => false,
                        _ => {
                            return Err(MtError::new(
                                ErrorCode::InvalidRequest,
                                format!("pretty must be true or false, not {v:?}"),
                            ));
                        }
                    }
                }
                // `device` and `removed` (assets) are taken and ignored.
                _ => {}
            }
        }
        if q.at.is_some() && q.interval.is_some() {
            return Err(MtError::new(
                ErrorCode::InvalidRequest,
                "'at' and 'interval' cannot go together",
            ));
        }
        Ok(q)
    }
}

/// One step of a `path`: an element name (or `*`), its predicates, and whether it may be any
/// descendant (`//`) rather than a child (`/`).
#[derive(Debug, Clone, PartialEq, Eq)]
struct Step {
    descendant: bool,
    name: String,
    preds: Vec<(String, String)>,
}

/// A `path` filter: the XPath forms the standard's examples use (Part 1, "path"): steps of
/// element names or `*`, joined by `/` or `//`, each with `[@attr="value"]` predicates
/// (several, or joined by `and`), alternatives joined by `|`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PathFilter {
    alternatives: Vec<Vec<Step>>,
}

/// One element on the way from the document's `Devices` down to a data item: its name and
/// the attributes a predicate may test.
pub type Node<'a> = (&'a str, Vec<(&'static str, &'a str)>);

impl PathFilter {
    /// Reads `path`; INVALID_PATH when it is not of the forms above.
    pub fn parse(path: &str) -> Result<PathFilter, MtError> {
        let bad = |why: &str| {
            MtError::new(
                ErrorCode::InvalidPath,
                format!("the path {path:?} could not be read: {why}"),
            )
        };
        let mut alternatives = Vec::new();
        for alt in split_top(path, '|') {
            let alt = alt.trim();
            if alt.is_empty() {
                return Err(bad("an empty alternative"));
            }
            let mut steps = Vec::new();
            let mut rest = alt;
            while !rest.is_empty() {
                let descendant = if let Some(r) = rest.strip_prefix("//") {
                    rest = r;
                    true
                } else if let Some(r) = rest.strip_prefix('/') {
                    rest = r;
                    false
                } else if steps.is_empty() {
                    // A relative path is read from the document's root, as a descendant.
                    true
                } else {
                    return Err(bad("steps are joined by / or //"));
                };
                let end = step_end(rest);
                let (step, r) = rest.split_at(end);
                rest = r;
                let (name, mut preds_text) = match step.find('[') {
                    Some(i) => (&step[..i], &step[i..]),
                    None => (step, ""),
                };
                if name.is_empty()
                    || !(name == "*" || name.chars().all(|c| c.is_ascii_alphanumeric()))
                {
                    return Err(bad("a step is an element name or *"));
                }
                let mut preds = Vec::new();
                while let Some(p) = preds_text.strip_prefix('[') {
                    let close = p.find(']').ok_or_else(|| bad("a [ without ]"))?;
                    for term in p[..close].split(" and ") {
                        preds.push(predicate(term.trim()).ok_or_else(|| {
                            bad("a predicate is @attribute=\"value\" (or 'value')")
                        })?);
                    }
                    preds_text = &p[close + 1..];
                }
                if !preds_text.is_empty() {
                    return Err(bad("text after a predicate"));
                }
                steps.push(Step {
                    descendant,
                    name: name.to_string(),
                    preds,
                });
            }
            alternatives.push(steps);
        }
        Ok(PathFilter { alternatives })
    }

    /// Whether the element at the end of `chain` (from `Devices` down), or one of its
    /// ancestors, is selected: a data item is taken when the path selects it or an element
    /// that holds it.
    pub fn selects(&self, chain: &[Node<'_>]) -> bool {
        self.alternatives
            .iter()
            .any(|steps| (1..=chain.len()).any(|k| matches(steps, &chain[..k])))
    }
}

/// Whether `steps` select exactly the last node of `chain`.
fn matches(steps: &[Step], chain: &[Node<'_>]) -> bool {
    let Some((last, before)) = steps.split_last() else {
        return chain.is_empty();
    };
    let Some((node, up)) = chain.split_last() else {
        return false;
    };
    if !step_takes(last, node) {
        return false;
    }
    if last.descendant {
        // Any ancestor chain (including none left over when it is the first step).
        (0..=up.len()).any(|k| matches_prefix(before, &up[..k]))
    } else {
        matches_prefix(before, up)
    }
}

fn matches_prefix(steps: &[Step], chain: &[Node<'_>]) -> bool {
    if steps.is_empty() {
        // The first step of an absolute path must start at the root: nothing above it but
        // the document element, which is not in the chain.
        return chain.is_empty();
    }
    matches(steps, chain)
}

fn step_takes(step: &Step, node: &Node<'_>) -> bool {
    (step.name == "*" || step.name == node.0)
        && step
            .preds
            .iter()
            .all(|(k, v)| node.1.iter().any(|(a, b)| a == k && b == v))
}

fn predicate(term: &str) -> Option<(String, String)> {
    let term = term.strip_prefix('@')?;
    let (k, v) = term.split_once('=')?;
    let v = v.trim();
    let v = v
        .strip_prefix('"')
        .and_then(|v| v.strip_suffix('"'))
        .or_else(|| v.strip_prefix('\'').and_then(|v| v.strip_suffix('\'')))?;
    Some((k.trim().to_string(), v.to_string()))
}

/// Where a step ends: at the next `/` outside brackets and quotes.
fn step_end(s: &str) -> usize {
    let (mut depth, mut quote) = (0, None);
    for (i, c) in s.char_indices() {
        match (c, quote) {
            ('"' | '\'', None) => quote = Some(c),
            (c, Some(q)) if c == q => quote = None,
            ('[', None) => depth += 1,
            (']', None) => depth -= 1,
            ('/', None) if depth == 0 => return i,
            _ => {}
        }
    }
    s.len()
}

/// `s` split at `sep` outside brackets and quotes.
fn split_top(s: &str, sep: char) -> Vec<&str> {
    let (mut depth, mut quote, mut start, mut out) = (0, None, 0, Vec::new());
    for (i, c) in s.char_indices() {
        match (c, quote) {
            ('"' | '\'', None) => quote = Some(c),
            (c, Some(q)) if c == q => quote = None,
            ('[', None) => depth += 1,
            (']', None) => depth -= 1,
            (c, None) if c == sep && depth == 0 => {
                out.push(&s[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    out.push(&s[start..]);
    out
}
