//! The machines: status, DI and DO.

use prost::Message as _;
use zenoh::bytes::ZBytes;

use super::{Client, ClientError, IO_TIMEOUT, no_reply};
use crate::bus::keys::MachineLeaf;
use crate::bus::payload::encoding;
use cellgate_core::pb;

impl Client {
    /// The status of one machine, or of every machine (`None`), sorted by name.
    pub async fn status(
        &self,
        machine: Option<&str>,
    ) -> Result<Vec<pb::MachineStatus>, ClientError> {
        let key = match machine {
            Some(m) => {
                Self::machine_arg(m)?;
                self.keys.leaf(m, MachineLeaf::Status)
            }
            None => self.keys.any_leaf(MachineLeaf::Status),
        };
        let what = match machine {
            Some(m) => format!("status of {m}"),
            None => "status".to_string(),
        };
        let asked = std::time::Instant::now();
        let mut all: Vec<pb::MachineStatus> = self
            .get_all(&what, &key, None, self.timeout)
            .await?
            .into_iter()
            .map(|(_, s)| s)
            .collect();
        if machine.is_some() && all.is_empty() {
            return Err(no_reply(&what, &key, self.timeout, asked.elapsed()));
        }
        all.sort_by(|a, b| a.machine.cmp(&b.machine));
        Ok(all)
    }

    /// Outputs DO on `machine` (SDO) with a get, and returns the status the gateway answers
    /// once SDO went out. `mask` `None` sets all 8 bits.
    pub async fn set_do(
        &self,
        machine: &str,
        value: u8,
        mask: Option<u8>,
    ) -> Result<pb::MachineStatus, ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::Do);
        let cmd = pb::DoCommand {
            value: u32::from(value),
            mask: mask.map(u32::from),
        };
        let payload = (cmd.encode_to_vec(), encoding::<pb::DoCommand>());
        self.get_one(&format!("DO of {machine}"), &key, Some(payload), IO_TIMEOUT)
            .await
    }

    /// Outputs DO with a put: no confirmation (the gateway logs a refusal).
    pub async fn put_do(
        &self,
        machine: &str,
        value: u8,
        mask: Option<u8>,
    ) -> Result<(), ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::Do);
        let cmd = pb::DoCommand {
            value: u32::from(value),
            mask: mask.map(u32::from),
        };
        let mut put = self
            .session
            .put(key.as_str(), cmd.encode_to_vec())
            .encoding(encoding::<pb::DoCommand>());
        if let Some(origin) = &self.origin {
            put = put.attachment(ZBytes::from(origin.clone()));
        }
        put.await.map_err(|source| ClientError::Zenoh {
            what: format!("put {key}"),
            source,
        })
    }

    /// Reads DI of `machine` now (RDI → SDI).
    pub async fn read_di(&self, machine: &str) -> Result<pb::DiImage, ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::Di);
        self.get_one(&format!("DI of {machine}"), &key, None, IO_TIMEOUT)
            .await
    }
}
