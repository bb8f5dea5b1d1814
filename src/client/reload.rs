//! Reloading the gateway's cell file (`P/C/@admin/reload`, permission `cell.reload`).

use std::time::Duration;

use prost::Message as _;

use super::{Client, ClientError};
use crate::bus::payload::encoding;
use cellgate_core::pb;

/// How long a reload may wait for its answer: the gateway starts the links of added machines
/// before it answers (up to 120 s there).
pub const RELOAD_TIMEOUT: Duration = Duration::from_secs(130);

impl Client {
    /// Asks the gateway to read its cell file again and apply what changed; `force`: stop or
    /// restart the links of removed and changed machines at once, failing their running jobs.
    /// A file that does not check, or that changes what needs a restart, is refused
    /// ([`ClientError::Refused`], every reason a line of its message) and changes nothing.
    pub async fn reload(&self, force: bool) -> Result<pb::ReloadResult, ClientError> {
        let key = self.keys.reload();
        let request = pb::ReloadRequest { force };
        let payload = (request.encode_to_vec(), encoding::<pb::ReloadRequest>());
        self.get_one("reload", &key, Some(payload), RELOAD_TIMEOUT)
            .await
    }
}
