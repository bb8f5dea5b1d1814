//! The agent's JSON documents: the XML documents' structure in JSON as the reference agent's
//! version 2 JSON writes it (`jsonVersion` 2): an element is an object, its attributes are
//! members, its text is `value`, and elements of one name are gathered in an array under it.

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
        if device.is_some_and(|want| want != d) {
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
            ("assetCount", J::from(0)),
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

/// `/current` or `/sample` as JSON.
pub fn streams(a: &Agent, obs: &[&Observation], next: u64, now_us: u64) -> String {
    let m = a.model();
    let buffer = a.buffer();
    let mut devices = Vec::new();
    for (d, comps) in a.grouped(obs) {
        let dev = &m.devices[d];
        let mut cs = Vec::new();
        for (c, list) in comps {
            let comp = &m.components[c];
            let mut o = Map::new();
            o.insert("component".into(), J::from(comp.element));
            o.insert("componentId".into(), J::from(comp.id.as_str()));
            if let Some(n) = &comp.name {
                o.insert("name".into(), J::from(n.as_str()));
            }
            for (cat, wrap) in [
                (Category::Sample, "Samples"),
                (Category::Event, "Events"),
                (Category::Condition, "Condition"),
            ] {
                let mut group = Map::new();
                for obs in list
                    .iter()
                    .filter(|o| m.items[o.item as usize].category == cat)
                {
                    let it = &m.items[obs.item as usize];
                    let mut e = Map::new();
                    e.insert("dataItemId".into(), J::from(it.id.as_str()));
                    e.insert("timestamp".into(), J::from(xml::timestamp(obs.time_us)));
                    e.insert("sequence".into(), J::from(obs.seq));
                    if let Some(n) = &it.name {
                        e.insert("name".into(), J::from(n.as_str()));
                    }
                    let element = match (&obs.value, cat) {
                        (Value::Cond(c), _) => {
                            e.insert("type".into(), J::from(it.kind));
                            if !c.native_code.is_empty() {
                                e.insert("nativeCode".into(), J::from(&*c.native_code));
                            }
                            if !c.text.is_empty() {
                                e.insert("value".into(), J::from(&*c.text));
                            }
                            c.level.element().to_string()
                        }
                        (_, Category::Condition) => {
                            e.insert("type".into(), J::from(it.kind));
                            "Unavailable".to_string()
                        }
                        (Value::Text(t), _) => {
                            e.insert("value".into(), J::from(&**t));
                            xml::element_of(it.kind)
                        }
                        _ => {
                            e.insert("value".into(), J::from("UNAVAILABLE"));
                            xml::element_of(it.kind)
                        }
                    };
                    push(&mut group, &element, J::Object(e));
                }
                if !group.is_empty() {
                    o.insert(wrap.into(), J::Object(group));
                }
            }
            cs.push(J::Object(o));
        }
        devices.push(json!({ "name": dev.name, "uuid": dev.uuid, "ComponentStream": cs }));
    }
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
    root("Streams", h, "Streams", json!({ "DeviceStream": devices }))
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

/// `/assets` as JSON: none kept.
pub fn assets(a: &Agent, now_us: u64) -> String {
    let h = header(
        a,
        now_us,
        &[
            ("assetBufferSize", J::from(super::agent::ASSET_BUFFER_SIZE)),
            ("assetCount", J::from(0)),
        ],
    );
    root("Assets", h, "Assets", json!({}))
}
