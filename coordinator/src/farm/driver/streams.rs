//! The job's `Cast` streams: one per (worker, dataset) pair it uses, opened with the scene
//! and read on a task of its own that turns every answer, and the stream's end, into the
//! job's [`Event`]s.

use std::time::Instant;

use prost::Message;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use trove_proto::convert::JOB_HEADER;
use trove_proto::v1 as pb;
use trove_proto::v1::worker_client::WorkerClient;

use super::super::registry::WorkerHandle;
use super::{Driver, Event, Stream};

impl Driver {
    /// Whether a stream carrying the scene to worker `id` is opening (not accepted yet).
    pub(super) fn scene_on_its_way(&self, id: &str) -> bool {
        self.opening.iter().any(|(k, _)| k.0 == id && self.streams.get(k).is_some_and(|s| s.carries_scene))
    }

    /// Opens the `Cast` stream to `worker` for dataset `d`: the scene first (by digest alone
    /// where the worker accepted it on another stream of the job), then batches.
    pub(super) fn open(&mut self, worker: &WorkerHandle, d: usize) {
        let (tx, rx) = mpsc::channel(256);
        let carries_scene = !self.scene_on.contains(&worker.id);
        let (scene_toml, scene_name, headers, shadow_maps) = if carries_scene {
            (
                self.plan.scene_toml.clone(),
                self.plan.scene_name.clone(),
                self.plan.headers.clone(),
                self.shadow_maps.clone().unwrap_or_default(),
            )
        } else {
            Default::default()
        };
        let open = pb::CastRequest {
            kind: Some(pb::cast_request::Kind::Open(pb::CastOpen {
                job_id: self.job.id.clone(),
                scene_toml,
                scene_name,
                dataset: d as u32,
                headers,
                scene_digest: self.scene_digest.clone(),
                shadow_maps,
                shadow_maps_computed: carries_scene && self.shadow_maps.is_some(),
            })),
        };
        self.tally.wire_to += open.encoded_len() as u64;
        self.tally.streams_opened += 1;
        self.tally.scenes_sent += u64::from(carries_scene);
        let _ = tx.try_send(open);
        let key = (worker.id.clone(), d);
        let mut client = WorkerClient::new(worker.channel.clone())
            .max_decoding_message_size(trove_proto::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(trove_proto::MAX_MESSAGE_BYTES);
        let mut request = tonic::Request::new(ReceiverStream::new(rx));
        if let Ok(value) = self.job.id.parse() {
            request.metadata_mut().insert(JOB_HEADER, value);
        }
        let events = self.events.clone();
        let stream_key = key.clone();
        self.next_serial += 1;
        let serial = self.next_serial;
        tokio::spawn(async move {
            let status = match client.cast(request).await {
                Ok(response) => {
                    let mut inbound = response.into_inner();
                    if events.send(Event::Opened { stream: stream_key.clone(), serial }).await.is_err() {
                        return;
                    }
                    loop {
                        match inbound.message().await {
                            Ok(Some(response)) => {
                                let bytes = response.encoded_len() as u64;
                                let stream = stream_key.clone();
                                if events.send(Event::Answer { stream, serial, response, bytes }).await.is_err() {
                                    return;
                                }
                            }
                            Ok(None) => break None,
                            Err(status) => break Some(status),
                        }
                    }
                }
                Err(status) => Some(status),
            };
            let _ = events.send(Event::StreamEnded { stream: stream_key, serial, status }).await;
        });
        self.opening.push((key.clone(), Instant::now()));
        self.streams.insert(key, Stream { tx, worker: worker.clone(), carries_scene, serial });
    }
}
