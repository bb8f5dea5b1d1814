use super::{Kind, classify};

#[test]
fn keys_are_read_back_to_their_cell_and_kind() {
    let k = |key: &str| classify("cellgate", key);
    assert_eq!(
        k("cellgate/demo/machine/mill-1/status"),
        Some(("demo".into(), Kind::Status))
    );
    assert_eq!(
        k("cellgate/demo/machine/mill-1/job/mill-1-1-1"),
        Some(("demo".into(), Kind::Job))
    );
    assert_eq!(
        k("cellgate/demo/plc/p/tag/t"),
        Some(("demo".into(), Kind::Tag))
    );
    assert_eq!(
        k("cellgate/demo/gateway"),
        Some(("demo".into(), Kind::Gateway))
    );
    assert_eq!(k("cellgate/demo/machine/mill-1/job/x/cancel"), None);
    assert_eq!(k("other/demo/gateway"), None);
}
