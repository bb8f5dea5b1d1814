//! The cell's history, audit trail and utilisation.

use super::{Client, ClientError, with_params};
use cellgate_core::pb;

impl Client {
    /// One page of the history (`audit`: of the audit trail) with these selector parameters
    /// (`_time`, `machine`, `kind`, `tag`, `limit`, `after`).
    pub async fn history(
        &self,
        audit: bool,
        params: &[(String, String)],
    ) -> Result<pb::HistoryPage, ClientError> {
        let base = if audit {
            self.keys.audit()
        } else {
            self.keys.history()
        };
        let key = with_params(base, params)?;
        let what = if audit {
            "the audit trail"
        } else {
            "the history"
        };
        self.get_one(what, &key, None, self.timeout).await
    }

    /// Utilisation with these selector parameters (`_time`, `machine`, `bucket`).
    pub async fn utilisation(
        &self,
        params: &[(String, String)],
    ) -> Result<pb::Utilisation, ClientError> {
        let key = with_params(self.keys.utilisation(), params)?;
        self.get_one("utilisation", &key, None, self.timeout).await
    }
}
