//! G05 streams: open, feed, status, cancel.

use prost::Message as _;
use zenoh::sample::Sample;

use super::{Client, ClientError};
use crate::bus::keys::{G05Part, MachineLeaf};
use crate::bus::payload::encoding;
use cellgate_core::pb;

impl Client {
    /// Opens a G05 stream on `machine` (`stream_id` empty: the gateway names it). With
    /// `producer_token`, the returned token keeps the stream alive: dropping it (or losing
    /// the connection) ends the stream with its end block.
    pub async fn g05_open(
        &self,
        machine: &str,
        stream_id: &str,
        producer_token: bool,
    ) -> Result<(pb::G05Opened, Option<zenoh::liveliness::LivelinessToken>), ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::G05);
        let request = pb::G05Open {
            stream_id: stream_id.to_string(),
            producer_token,
        };
        let payload = (request.encode_to_vec(), encoding::<pb::G05Open>());
        let opened: pb::G05Opened = self
            .get_one(
                &format!("G05 stream on {machine}"),
                &key,
                Some(payload),
                self.timeout,
            )
            .await?;
        let token = if producer_token {
            let key = self.keys.g05(machine, &opened.stream_id, G05Part::Producer);
            let token = self
                .session
                .liveliness()
                .declare_token(key.as_str())
                .await
                .map_err(|source| ClientError::Zenoh {
                    what: format!("liveliness token {key}"),
                    source,
                })?;
            Some(token)
        } else {
            None
        };
        Ok((opened, token))
    }

    /// Sends a batch of a stream (a put: express; errors show in the stream's status).
    pub async fn g05_batch(
        &self,
        machine: &str,
        stream: &str,
        batch: &pb::G05Batch,
    ) -> Result<(), ClientError> {
        let key = self.keys.g05(machine, stream, G05Part::Blocks);
        self.session
            .put(key.as_str(), batch.encode_to_vec())
            .encoding(encoding::<pb::G05Batch>())
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .express(true)
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("put {key}"),
                source,
            })
    }

    /// Sends a batch of a stream and waits for the gateway's answer: the stream's status with
    /// the batch taken, or the refusal (a travel out of range, no credits, a gap).
    pub async fn g05_batch_acked(
        &self,
        machine: &str,
        stream: &str,
        batch: &pb::G05Batch,
    ) -> Result<pb::G05Status, ClientError> {
        let key = self.keys.g05(machine, stream, G05Part::Blocks);
        let payload = (batch.encode_to_vec(), encoding::<pb::G05Batch>());
        self.get_one(
            &format!("batch {} of G05 stream {stream}", batch.seq),
            &key,
            Some(payload),
            self.timeout,
        )
        .await
    }

    /// Follows a stream's status.
    pub async fn g05_status(
        &self,
        machine: &str,
        stream: &str,
    ) -> Result<zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<Sample>>, ClientError>
    {
        self.subscribe(&self.keys.g05(machine, stream, G05Part::Status))
            .await
    }

    /// Cancels a stream: the gateway sends the end block and frees the machine.
    pub async fn g05_cancel(&self, machine: &str, stream: &str) -> Result<(), ClientError> {
        let key = self.keys.g05(machine, stream, G05Part::Status);
        self.session
            .delete(key.as_str())
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("delete {key}"),
                source,
            })
    }
}
