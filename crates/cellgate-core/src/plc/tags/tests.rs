use std::time::{Duration, SystemTime};

use super::*;
use crate::config::Real;

fn tag(name: &str, module: Module, address: u16, kind: TagType) -> TagConfig {
    TagConfig {
        name: name.to_string(),
        station: 0,
        module,
        address,
        kind,
        bit: None,
        scale: Real(1.0),
        poll_ms: 100,
        deadband: Real(0.0),
        writable: false,
        history: false,
        mtconnect: None,
    }
}

#[test]
fn adjacent_tags_share_a_read_up_to_212_bytes() {
    // 120 u16 tags at D0..D119 are 240 bytes: two reads, the first of 106 words (212 bytes).
    let tags: Vec<TagConfig> = (0..120)
        .map(|i| tag(&format!("t{i}"), Module::D, i, TagType::U16))
        .collect();
    let groups = plan(&tags);
    assert_eq!(groups.len(), 1);
    let reads: Vec<(u16, u16)> = groups[0]
        .reads
        .iter()
        .map(|r| (r.address, r.words))
        .collect();
    assert_eq!(reads, [(0, 106), (106, 14)]);

    // Different intervals, stations or modules are different reads.
    let mut a = tag("a", Module::D, 0, TagType::U16);
    let mut b = tag("b", Module::D, 1, TagType::U32);
    let c = tag("c", Module::M, 2, TagType::Bit);
    b.poll_ms = 500;
    a.station = 0;
    let groups = plan(&[a, b, c]);
    assert_eq!(groups.len(), 2);
    assert_eq!(groups[0].reads.len(), 2);
    assert_eq!(
        (groups[1].reads[0].address, groups[1].reads[0].words),
        (1, 2)
    );
}

#[test]
fn every_type_decodes_and_encodes_back() {
    let cases = [
        (TagType::U16, Module::D, 0xFFFF_i64),
        (TagType::I16, Module::D, -2),
        (TagType::U32, Module::D, 0x1234_5678),
        (TagType::I32, Module::D, -100_000),
        (TagType::Bcd, Module::D, 9_876),
        (TagType::U32, Module::TS, 0x8765_4321),
        (TagType::I32, Module::TS, -7),
        (TagType::Bcd, Module::TS, 12_345_678),
    ];
    for (kind, module, raw) in cases {
        let words = encode(kind, module, raw);
        assert_eq!(
            decode(kind, module, 0, &words),
            Some(raw),
            "{kind:?} {module}"
        );
    }
    // 32 bits in a 16-bit area: low word first.
    assert_eq!(
        encode(TagType::U32, Module::D, 0x1234_5678),
        [0x5678, 0x1234]
    );
    assert_eq!(decode(TagType::Bit, Module::M, 3, &[0b1000]), Some(1));
    assert_eq!(decode(TagType::Bit, Module::M, 2, &[0b1000]), Some(0));
    // A BCD nibble above 9 is no value.
    assert_eq!(decode(TagType::Bcd, Module::D, 0, &[0x00A1]), None);
}

#[test]
fn changes_publish_only_beyond_the_deadband() {
    let mut t = tag("temp", Module::D, 10, TagType::U16);
    t.scale = Real(0.1);
    t.deadband = Real(0.5);
    let mut table = TagTable::new("plc", &[t]);
    let now = SystemTime::UNIX_EPOCH + Duration::from_secs(1000);
    let read = |table: &mut TagTable, raw: u32| {
        table
            .apply_read(0, 0, Some(&[raw]), now)
            .iter()
            .map(|v| v.value.unwrap())
            .collect::<Vec<f64>>()
    };
    assert_eq!(read(&mut table, 200), [20.0]);
    assert!(
        read(&mut table, 200).is_empty(),
        "no change, nothing published"
    );
    assert!(
        read(&mut table, 204).is_empty(),
        "0.4 is inside the deadband"
    );
    assert_eq!(read(&mut table, 205), [20.5]);
    assert!(
        read(&mut table, 201).is_empty(),
        "0.4 from the last published value"
    );
    // A failed read turns the quality stale (published once), and a good one back.
    let stale = table.apply_read(0, 0, None, now);
    assert_eq!(stale.len(), 1);
    assert_eq!(stale[0].quality, Quality::Stale);
    assert!(table.apply_read(0, 0, None, now).is_empty());
    let down = table.station_down(0);
    assert_eq!(down[0].quality, Quality::StationDown);
    let good = table.apply_read(0, 0, Some(&[201]), now);
    assert_eq!(good[0].quality, Quality::Good);
    assert_eq!(table.get("temp").unwrap().time, Some(now));
}

#[test]
fn writes_undo_the_scale_check_the_range_and_refuse_read_only_tags() {
    let mut w = tag("speed", Module::D, 4, TagType::I16);
    w.scale = Real(0.5);
    w.writable = true;
    let mut bit = tag("lamp", Module::M, 1, TagType::Bit);
    bit.bit = Some(5);
    bit.writable = true;
    let ro = tag("count", Module::D, 0, TagType::U16);
    let table = TagTable::new("plc", &[w, bit, ro]);
    assert_eq!(
        table.plan_write("speed", -10.0).unwrap().op,
        WriteOp::Words(vec![0xFFEC])
    );
    assert!(matches!(
        table.plan_write("speed", 20_000.0),
        Err(TagError::OutOfRange { .. })
    ));
    assert_eq!(
        table.plan_write("lamp", 1.0).unwrap().op,
        WriteOp::Bit { bit: 5, on: true }
    );
    assert!(matches!(
        table.plan_write("lamp", 2.0),
        Err(TagError::OutOfRange { .. })
    ));
    assert!(matches!(
        table.plan_write("count", 1.0),
        Err(TagError::ReadOnly { .. })
    ));
    assert!(matches!(
        table.plan_write("nope", 1.0),
        Err(TagError::Unknown { .. })
    ));
}

#[test]
fn a_write_is_in_range_as_given_and_echoed_as_the_tag_will_read() {
    let mut recipe = tag("recipe", Module::D, 0, TagType::U16);
    recipe.writable = true;
    let mut temp = tag("temp", Module::D, 1, TagType::I16);
    temp.scale = Real(0.1);
    temp.writable = true;
    let table = TagTable::new("plc", &[recipe, temp]);
    // Rounded into range is not in range: an unsigned tag takes no -0.4, nor 65535.4.
    for v in [-0.4, 65_535.4] {
        assert!(
            matches!(
                table.plan_write("recipe", v),
                Err(TagError::OutOfRange { .. })
            ),
            "{v}"
        );
    }
    assert_eq!(table.plan_write("recipe", 65_535.0).unwrap().raw, 65_535);
    // Finer than the scale: written rounded, and said so.
    let w = table.plan_write("temp", 12.34).unwrap();
    assert_eq!(w.raw, 123);
    assert!((w.value() - 12.3).abs() < 1e-9, "{}", w.value());
    // The scale's binary fractions do not push the top of the range out.
    assert_eq!(table.plan_write("temp", 3276.7).unwrap().raw, 32_767);
}
