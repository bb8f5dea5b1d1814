//! The agent's JSON documents: the XML documents' structure in JSON as the reference agent's
//! version 2 JSON writes it (`jsonVersion` 2): an element is an object, its attributes are
//! members, its text is `value`, and elements of one name are gathered in an array under it.

use std::fmt::Write as _;

use serde_json::{Map, Value as J, json};

use super::agent::Agent;
use super::buffer::{Observation, Value};
use super::model::Category;
use super::request::MtError;
use super::xml;

fn header(a: &Agent, now_us: u64, extra: &[(&str, J)]) -> J {
    let mut h = Map::new();
    for (k, v) in a.header_attrs(now_us) {
        let v = match k {
            "instanceId" | "bufferSize" => v.parse::<u64>().map_or(J::from(v), J::from),
            _ => J::from(v),
        };
        h.insert(k.to_string(), v);
    }
    for (k, v) in extra {
        h.insert((*k).to_string(), v.clone());
    }
    J::Object(h)
}

fn root(kind: &str, header: J, body_key: &str, body: J) -> String {
    json!({
        format!("MTConnect{kind}"): {
            "jsonVersion": 2,
            "schemaVersion": "2.5",
            "Header": header,
            body_key: body,
        }
    })
    .to_string()
}

/// Pushes `value` into the array `obj[key]`.
fn push(obj: &mut Map<String, J>, key: &str, value: J) {
    if let J::Array(a) = obj
        .entry(key.to_string())
        .or_insert_with(|| J::Array(Vec::new()))
    {
        a.push(value);
    }
}

/// `/probe` as JSON.
pub fn probe(a: &Agent, device: Option<usize>, now_us: u64) -> String {
    let m = a.model();
    let mut devices = Map::new();
    for (d, dev) in m.devices.iter().enumerate() {
        if device.is_some_and(|want| want != d) || dev.removed {
            continue;
        }
        let comp = &m.components[dev.component];
        let mut o = component(a, dev.component);
        o.insert("uuid".into(), J::from(dev.uuid.as_str()));
        o.insert("Description".into(), json!({ "value": dev.description }));
        push(&mut devices, comp.element, J::Object(o));
    }
    let h = header(
        a,
        now_us,
        &[
            ("assetBufferSize", J::from(super::agent::ASSET_BUFFER_SIZE)),
            ("assetCount", J::from(a.kept_assets().len())),
            ("deviceModelChangeTime", J::from(a.model_change_time())),
        ],
    );
    root("Devices", h, "Devices", J::Object(devices))
}

fn component(a: &Agent, c: usize) -> Map<String, J> {
    let m = a.model();
    let comp = &m.components[c];
    let mut o = Map::new();
    o.insert("id".into(), J::from(comp.id.as_str()));
    if let Some(n) = &comp.name {
        o.insert("name".into(), J::from(n.as_str()));
    }
    if !comp.items.is_empty() {
        let items: Vec<J> = comp
            .items
            .iter()
            .map(|&i| {
                let it = &m.items[i];
                let mut d = Map::new();
                d.insert("category".into(), J::from(it.category.name()));
                d.insert("id".into(), J::from(it.id.as_str()));
                d.insert("type".into(), J::from(it.kind));
                if let Some(n) = &it.name {
                    d.insert("name".into(), J::from(n.as_str()));
                }
                if let Some(u) = it.units {
                    d.insert("units".into(), J::from(u));
                }
                if let Some(n) = &it.native_name {
                    d.insert("Source".into(), json!({ "value": n }));
                }
                J::Object(d)
            })
            .collect();
        o.insert("DataItems".into(), json!({ "DataItem": items }));
    }
    if !comp.children.is_empty() {
        let mut children = Map::new();
        for &ch in &comp.children {
            push(
                &mut children,
                m.components[ch].element,
                J::Object(component(a, ch)),
            );
        }
        o.insert("Components".into(), J::Object(children));
    }
    o
}

/// `s` as a JSON string, quoted and escaped (RFC 8259 §7).
fn string(out: &mut String, s: &str) {
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => {
                let _ = write!(out, "\\u{:04x}", c as u32);
            }
            c => out.push(c),
        }
    }
    out.push('"');
}

/// `"key":"value"`, after a comma unless `first`.
fn member(out: &mut String, key: &str, value: &str) {
    string(out, key);
    out.push(':');
    string(out, value);
}

/// One observation as its JSON object.
fn observation(out: &mut String, a: &Agent, o: &Observation) {
    let it = &a.model().items[o.item as usize];
    out.push('{');
    member(out, "dataItemId", &it.id);
    out.push(',');
    member(out, "timestamp", &xml::timestamp(o.time_us));
    let _ = write!(out, ",\"sequence\":{}", o.seq);
    if let Some(n) = &it.name {
        out.push(',');
        member(out, "name", n);
    }
    match (&o.value, it.category) {
        (Value::Cond(c), _) => {
            out.push(',');
            member(out, "type", it.kind);
            if !c.native_code.is_empty() {
                out.push(',');
                member(out, "nativeCode", &c.native_code);
            }
            if !c.text.is_empty() {
                out.push(',');
                member(out, "value", &c.text);
            }
        }
        (_, Category::Condition) => {
            out.push(',');
            member(out, "type", it.kind);
        }
        (Value::Text(t), _) => {
            out.push(',');
            member(out, "value", t);
        }
        _ => {
            out.push(',');
            member(out, "value", "UNAVAILABLE");
        }
    }
    out.push('}');
}

/// The element an observation is in a document.
fn element(a: &Agent, o: &Observation) -> String {
    let it = &a.model().items[o.item as usize];
    match (&o.value, it.category) {
        (Value::Cond(c), _) => c.level.element().to_string(),
        (_, Category::Condition) => "Unavailable".to_string(),
        _ => xml::element_of(it.kind),
    }
}

/// `/current` or `/sample` as JSON, written straight into the text (a thousand machines'
/// `/current` would otherwise build a tree of every member first).
pub fn streams(a: &Agent, obs: &[&Observation], next: u64, now_us: u64) -> String {
    let m = a.model();
    let buffer = a.buffer();
    let mut out = String::with_capacity(1024 + obs.len() * 160);
    out.push('[');
    for (n, (d, comps)) in a.grouped(obs).into_iter().enumerate() {
        let dev = &m.devices[d];
        if n > 0 {
            out.push(',');
        }
        out.push('{');
        member(&mut out, "name", &dev.name);
        out.push(',');
        member(&mut out, "uuid", &dev.uuid);
        out.push_str(",\"ComponentStream\":[");
        for (k, (c, list)) in comps.into_iter().enumerate() {
            let comp = &m.components[c];
            if k > 0 {
                out.push(',');
            }
            out.push('{');
            member(&mut out, "component", comp.element);
            out.push(',');
            member(&mut out, "componentId", &comp.id);
            if let Some(name) = &comp.name {
                out.push(',');
                member(&mut out, "name", name);
            }
            for (cat, wrap) in [
                (Category::Sample, "Samples"),
                (Category::Event, "Events"),
                (Category::Condition, "Condition"),
            ] {
                // Observations of one element gathered in an array, in the order first met.
                let mut groups: Vec<(String, Vec<&Observation>)> = Vec::new();
                for o in list
                    .iter()
                    .filter(|o| m.items[o.item as usize].category == cat)
                {
                    let e = element(a, o);
                    match groups.iter_mut().find(|(g, _)| *g == e) {
                        Some((_, v)) => v.push(o),
                        None => groups.push((e, vec![o])),
                    }
                }
                if groups.is_empty() {
                    continue;
                }
                out.push(',');
                string(&mut out, wrap);
                out.push_str(":{");
                for (g, (e, list)) in groups.iter().enumerate() {
                    if g > 0 {
                        out.push(',');
                    }
                    string(&mut out, e);
                    out.push_str(":[");
                    for (i, o) in list.iter().enumerate() {
                        if i > 0 {
                            out.push(',');
                        }
                        observation(&mut out, a, o);
                    }
                    out.push(']');
                }
                out.push('}');
            }
            out.push('}');
        }
        out.push_str("]}");
    }
    out.push(']');
    let h = header(
        a,
        now_us,
        &[
            ("nextSequence", J::from(next)),
            ("firstSequence", J::from(buffer.first())),
            ("lastSequence", J::from(buffer.last())),
            ("deviceModelChangeTime", J::from(a.model_change_time())),
        ],
    );
    // The document around the streams, as `root` writes the others.
    format!(
        "{{\"MTConnectStreams\":{{\"jsonVersion\":2,\"schemaVersion\":\"2.5\",\"Header\":{h},\"Streams\":{{\"DeviceStream\":{out}}}}}}}"
    )
}

/// An error as JSON.
pub fn error(a: &Agent, e: &MtError, now_us: u64) -> String {
    let h = header(a, now_us, &[]);
    root(
        "Error",
        h,
        "Errors",
        json!({ "Error": [{ "errorCode": e.code.name(), "value": e.message }] }),
    )
}

/// `/assets` as JSON.
pub fn assets(a: &Agent, list: &[&super::assets::FileAsset], now_us: u64) -> String {
    let h = header(
        a,
        now_us,
        &[
            ("assetBufferSize", J::from(super::agent::ASSET_BUFFER_SIZE)),
            ("assetCount", J::from(a.kept_assets().len())),
        ],
    );
    let files: Vec<J> = list
        .iter()
        .map(|f| {
            json!({
                "assetId": f.asset_id,
                "timestamp": xml::timestamp(f.time_us),
                "deviceUuid": a.model().devices[f.device].uuid,
                "name": f.name,
                "mediaType": "text/plain",
                "applicationCategory": "DEVICE",
                "applicationType": "PRODUCTION_PROGRAM",
                "size": f.size,
                "versionId": f.version,
                "state": f.state(),
                "FileLocation": { "href": f.location },
                "CreationTime": xml::timestamp(f.time_us),
            })
        })
        .collect();
    let body = if files.is_empty() {
        json!({})
    } else {
        json!({ "File": files })
    };
    root("Assets", h, "Assets", body)
}
