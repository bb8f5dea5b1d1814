//! Documents laid out for a person to read (`pretty=true`, Part 1 "Request"): the same
//! document, indented two spaces a level. Documents are written compact; this lays one out
//! after the fact, so both forms carry the same content.

use quick_xml::Writer;
use quick_xml::events::Event;
use quick_xml::reader::Reader;

use super::Format;

/// `doc` laid out, or `doc` as it is should it not read back (it always does: it is ours).
pub fn pretty(format: Format, doc: &str) -> String {
    match format {
        Format::Xml => xml(doc).unwrap_or_else(|| doc.to_string()),
        Format::Json => json(doc),
    }
}

/// Each element on a line of its own, indented; an element's text stays on its line.
fn xml(doc: &str) -> Option<String> {
    let mut reader = Reader::from_str(doc);
    let mut w = Writer::new_with_indent(Vec::with_capacity(doc.len() * 5 / 4), b' ', 2);
    loop {
        match reader.read_event().ok()? {
            Event::Eof => break,
            e => w.write_event(e).ok()?,
        }
    }
    String::from_utf8(w.into_inner()).ok()
}

/// A member or element a line, indented; `key: value` with a space; an empty object or
/// list stays `{}` / `[]`. Strings are copied as they are, escapes and all.
fn json(doc: &str) -> String {
    let mut out = String::with_capacity(doc.len() * 3 / 2);
    let mut depth = 0usize;
    let mut in_string = false;
    let mut escaped = false;
    let mut chars = doc.chars().peekable();
    let newline = |out: &mut String, depth: usize| {
        out.push('\n');
        out.extend(std::iter::repeat_n(' ', depth * 2));
    };
    while let Some(c) = chars.next() {
        if in_string {
            out.push(c);
            match (escaped, c) {
                (true, _) => escaped = false,
                (false, '\\') => escaped = true,
                (false, '"') => in_string = false,
                _ => {}
            }
            continue;
        }
        match c {
            '"' => {
                in_string = true;
                out.push(c);
            }
            '{' | '[' => {
                out.push(c);
                let close = if c == '{' { '}' } else { ']' };
                if chars.peek() == Some(&close) {
                    out.push(close);
                    chars.next();
                } else {
                    depth += 1;
                    newline(&mut out, depth);
                }
            }
            '}' | ']' => {
                depth = depth.saturating_sub(1);
                newline(&mut out, depth);
                out.push(c);
            }
            ',' => {
                out.push(c);
                newline(&mut out, depth);
            }
            ':' => out.push_str(": "),
            c if c.is_whitespace() => {}
            c => out.push(c),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xml_is_indented_and_reads_back_the_same() {
        let doc = r#"<?xml version="1.0" encoding="UTF-8"?><A x="1"><B>t &amp; u</B><C/><D><E>1</E></D></A>"#;
        let p = pretty(Format::Xml, doc);
        assert_eq!(
            p,
            "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<A x=\"1\">\n  <B>t &amp; u</B>\n  <C/>\n  <D>\n    <E>1</E>\n  </D>\n</A>"
        );
    }

    #[test]
    fn json_is_indented_and_parses_to_the_same_value() {
        let doc = r#"{"a":[1,{"b":"x, y: {z}\"]"}],"c":{},"d":[]}"#;
        let p = pretty(Format::Json, doc);
        assert_eq!(
            p,
            "{\n  \"a\": [\n    1,\n    {\n      \"b\": \"x, y: {z}\\\"]\"\n    }\n  ],\n  \"c\": {},\n  \"d\": []\n}"
        );
        let a: serde_json::Value = serde_json::from_str(doc).unwrap();
        let b: serde_json::Value = serde_json::from_str(&p).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn empty_and_odd_input_do_not_panic() {
        for doc in ["", "<", "{", "}}]]", "\"", "<a><b></a>"] {
            let _ = pretty(Format::Xml, doc);
            let _ = pretty(Format::Json, doc);
        }
    }
}
