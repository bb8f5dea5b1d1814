//! The agent's XML documents (MTConnect Part 1, "Response Documents"): Devices, Streams,
//! Assets and Error, in the 2.5 namespaces, written with quick-xml (which escapes text and
//! attribute values).

use quick_xml::Writer;
use quick_xml::events::{BytesDecl, BytesEnd, BytesStart, BytesText, Event};

/// The version every document's header gives (Part 1: major.minor.revision.build).
pub const VERSION: &str = "2.5.0.0";

/// A document being written into memory.
pub struct Xml {
    w: Writer<Vec<u8>>,
}

impl Xml {
    /// A document whose root element `root` is of the `kind` namespace (`Devices`, `Streams`,
    /// `Assets`, `Error`).
    pub fn new(kind: &str, capacity: usize) -> Xml {
        let mut x = Xml {
            w: Writer::new(Vec::with_capacity(capacity)),
        };
        // Writing into a Vec<u8> cannot fail: the io::Result of each event is always Ok.
        let _ =
            x.w.write_event(Event::Decl(BytesDecl::new("1.0", Some("UTF-8"), None)));
        let ns = format!("urn:mtconnect.org:MTConnect{kind}:2.5");
        let location =
            format!("{ns} https://schemas.mtconnect.org/schemas/MTConnect{kind}_2.5.xsd");
        x.open(
            &format!("MTConnect{kind}"),
            &[
                ("xmlns", ns.as_str()),
                ("xmlns:m", ns.as_str()),
                ("xmlns:xsi", "http://www.w3.org/2001/XMLSchema-instance"),
                ("xsi:schemaLocation", location.as_str()),
            ],
        );
        x
    }

    /// `<name attrs…>`.
    pub fn open(&mut self, name: &str, attrs: &[(&str, &str)]) {
        let e = BytesStart::new(name).with_attributes(attrs.iter().copied());
        let _ = self.w.write_event(Event::Start(e));
    }

    /// `</name>`.
    pub fn close(&mut self, name: &str) {
        let _ = self.w.write_event(Event::End(BytesEnd::new(name)));
    }

    /// `<name attrs…/>`.
    pub fn empty(&mut self, name: &str, attrs: &[(&str, &str)]) {
        let e = BytesStart::new(name).with_attributes(attrs.iter().copied());
        let _ = self.w.write_event(Event::Empty(e));
    }

    /// `<name attrs…>text</name>`, or empty when `text` is.
    pub fn text(&mut self, name: &str, attrs: &[(&str, &str)], text: &str) {
        if text.is_empty() {
            return self.empty(name, attrs);
        }
        self.open(name, attrs);
        let _ = self.w.write_event(Event::Text(BytesText::new(text)));
        self.close(name);
    }

    /// A piece of XML without declaration or root (an asset on an SHDR line).
    pub fn fragment(capacity: usize) -> Xml {
        Xml {
            w: Writer::new(Vec::with_capacity(capacity)),
        }
    }

    /// The piece written so far ([`Xml::fragment`]).
    pub fn finish_fragment(self) -> String {
        String::from_utf8(self.w.into_inner()).unwrap_or_default()
    }

    /// Closes the root and returns the document.
    pub fn finish(mut self, kind: &str) -> String {
        self.close(&format!("MTConnect{kind}"));
        String::from_utf8(self.w.into_inner()).unwrap_or_default()
    }
}

/// An observation's element name from its type: `PART_COUNT` → `PartCount`.
pub fn element_of(kind: &str) -> String {
    let mut out = String::with_capacity(kind.len());
    for word in kind.split('_') {
        let mut cs = word.chars();
        if let Some(c) = cs.next() {
            out.push(c.to_ascii_uppercase());
            out.extend(cs.map(|c| c.to_ascii_lowercase()));
        }
    }
    out
}

/// Microseconds since the Unix epoch as the standard's timestamps: UTC, ISO 8601, with
/// microseconds (`2026-01-31T12:00:00.123456Z`).
pub fn timestamp(time_us: u64) -> String {
    let secs = time_us / 1_000_000;
    let (days, rem) = (secs / 86_400, secs % 86_400);
    let (y, m, d) = crate::program::punch::civil_from_days(days);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}.{:06}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60,
        time_us % 1_000_000
    )
}
