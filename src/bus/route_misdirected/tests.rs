use super::*;

fn keys() -> CellKeys {
    CellKeys::new("cellgate", "demo").unwrap()
}

#[test]
fn each_read_key_with_a_write_beside_it_names_that_write() {
    let k = keys();
    let cases = [
        (
            "cellgate/demo/program/O1000",
            "program",
            "cellgate/demo/program/O1000/write",
        ),
        (
            "cellgate/demo/machine/mill-1/job",
            "job",
            "cellgate/demo/machine/mill-1/submit",
        ),
        (
            "cellgate/demo/plc/press/tag/speed",
            "plc.tag",
            "cellgate/demo/plc/press/tag/speed/set",
        ),
        (
            "cellgate/demo/plc/press/mem/1/D",
            "plc.mem",
            "cellgate/demo/plc/press/mem/1/D/write",
        ),
        (
            "cellgate/demo/plc/press/mem/1/D/100",
            "plc.mem",
            "cellgate/demo/plc/press/mem/1/D/100/write",
        ),
        (
            "cellgate/demo/plc/press/transfer/3",
            "plc.transfer",
            "cellgate/demo/plc/press/transfer/3/send",
        ),
        (
            "cellgate/demo/plc/press/message",
            "plc.message",
            "cellgate/demo/plc/press/message/send",
        ),
    ];
    for (key, kind, write) in cases {
        let m = misdirected(&k, key).unwrap_or_else(|| panic!("{key}"));
        assert_eq!((m.kind, m.write_key.as_str()), (kind, write), "{key}");
    }
}

#[test]
fn write_keys_and_keys_without_a_write_are_not_misdirected() {
    let k = keys();
    for key in [
        "cellgate/demo/program/O1000/write",
        "cellgate/demo/machine/mill-1/submit",
        "cellgate/demo/machine/mill-1/status",
        "cellgate/demo/plc/press/tag/speed/set",
        "cellgate/demo/plc/press/mem/1/D/write",
        "cellgate/demo/plc/press/transfer/3/send",
        "cellgate/demo/plc/press/message/send",
        "cellgate/demo/plc/press/status",
        "cellgate/other/program/O1000",
    ] {
        assert_eq!(misdirected(&k, key), None, "{key}");
    }
}
