//! The cell's key expressions: the grammar is the core's ([`cellgate_core::keys`], built and
//! parsed there, with no zenoh in it, so clients and the fuzz targets share it); this module
//! adds what needs zenoh's own key expressions, and checks that zenoh agrees with the grammar.

pub use cellgate_core::keys::*;

use zenoh::key_expr::{KeyExpr, keyexpr};

/// Whether a query's key expression `query` takes in the concrete key `key`.
pub fn intersects(query: &KeyExpr<'_>, key: &str) -> bool {
    keyexpr::new(key).is_ok_and(|k| query.intersects(k))
}

/// `P/C/program/NAME/changed`: the gateway publishes the program's `ProgramInfo` once a
/// store, adoption or removal of it is on disk, whoever asked (a get or a put on its write
/// key, the console); the requester's `RequestOrigin` is the sample's attachment.
pub fn program_changed(keys: &CellKeys, name: &str) -> String {
    format!("{}/program/{name}/changed", keys.root())
}

/// `P/C/machine/M/do/out`: the gateway publishes a `DoCommand` once its SDO went out on a
/// get (a put on `…/do` is itself the event); the requester's `RequestOrigin` is the
/// sample's attachment.
pub fn do_out(keys: &CellKeys, machine: &str) -> String {
    format!("{}/out", keys.leaf(machine, MachineLeaf::Do))
}

/// Which of the two event keys above `key` is: `(true, NAME)` for a program's, `(false, M)`
/// for a machine's DO output.
pub fn parse_event<'k>(keys: &CellKeys, key: &'k str) -> Option<(bool, &'k str)> {
    let rest = key.strip_prefix(keys.root())?.strip_prefix('/')?;
    match rest.split('/').collect::<Vec<_>>().as_slice() {
        ["program", name, "changed"] => Some((true, name)),
        ["machine", m, "do", "out"] => Some((false, m)),
        _ => None,
    }
}

#[cfg(test)]
mod tests;
