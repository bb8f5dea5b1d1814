//! The cell's key expressions: the grammar is the core's ([`cellgate_core::keys`], built and
//! parsed there, with no zenoh in it, so clients and the fuzz targets share it); this module
//! adds what needs zenoh's own key expressions, and checks that zenoh agrees with the grammar.

pub use cellgate_core::keys::*;

use zenoh::key_expr::{KeyExpr, keyexpr};

/// Whether a query's key expression `query` takes in the concrete key `key`.
pub fn intersects(query: &KeyExpr<'_>, key: &str) -> bool {
    keyexpr::new(key).is_ok_and(|k| query.intersects(k))
}

#[cfg(test)]
mod tests;
