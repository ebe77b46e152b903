//! The shadow pass of a job whose scene has shadows (SPEC §6, trove-core `render::shadow`):
//! before any band, each dataset whose objects shade some lattice asks one of its holders
//! for their factors (`Shadow`), trying the next holder when one fails; the coordinator
//! multiplies them in object order (`ShadowPlan::combine`, as local mode does, so the maps
//! are the same f32s) and the job's streams carry the maps with the scene.

use std::time::Instant;

use prost::Message;
use tokio::task::JoinSet;
use trove_core::render::shadow::{Factors, ShadowPlan};
use trove_proto::convert;
use trove_proto::v1 as pb;
use trove_proto::v1::worker_client::WorkerClient;

use super::super::registry::WorkerHandle;
use super::{Driver, JobError};

impl Driver {
    /// Computes the scene's shadow maps on the workers, when it has shadows; from then on
    /// the streams carry them with the scene, and the scene's digest covers them.
    pub(super) async fn shadow_pass(&mut self) -> Result<(), JobError> {
        let scene = self.plan.scene.clone();
        let plan = ShadowPlan::of(&scene);
        if plan.is_empty() {
            return Ok(());
        }
        let started = Instant::now();
        let mut asks = JoinSet::new();
        for d in plan.datasets_with_work(&scene) {
            let holders: Vec<WorkerHandle> = self
                .registry
                .holders(&self.plan.dataset_keys[d])
                .iter()
                .filter_map(|id| self.registry.handle(id))
                .collect();
            let open = pb::CastOpen {
                job_id: self.job.id.clone(),
                scene_toml: self.plan.scene_toml.clone(),
                scene_name: self.plan.scene_name.clone(),
                dataset: d as u32,
                headers: self.plan.headers.clone(),
                scene_digest: self.scene_digest.clone(),
                shadow_maps: Vec::new(),
                shadow_maps_computed: false,
            };
            self.tally.wire_to += open.encoded_len() as u64;
            let dataset = scene.datasets()[d].name().to_string();
            asks.spawn(ask(holders, open, dataset));
        }
        let mut factors = Vec::new();
        while let Some(answer) = asks.join_next().await {
            let (worker, reply) = answer.map_err(|e| JobError::Internal(format!("a shadow request failed: {e}")))??;
            self.tally.wire_from += reply.encoded_len() as u64;
            for f in reply.factors {
                let bad = || JobError::Worker {
                    worker: worker.clone(),
                    failure: Box::new(convert::failure(
                        pb::Reason::BadBatch,
                        false,
                        format!("its shadow factors of object {} do not fit the scene's plan", f.occluder),
                    )),
                };
                let len = plan.lattices().get(f.lattice as usize).map(|l| l.len()).ok_or_else(bad)?;
                let values = convert::from_unit_runs(&f.values, len).ok_or_else(bad)?;
                factors.push(Factors { lattice: f.lattice as usize, occluder: f.occluder as usize, values });
            }
        }
        let maps = plan.combine(&scene, factors).map_err(|e| JobError::Worker {
            worker: "(a shadow answer)".into(),
            failure: Box::new(convert::failure(pb::Reason::BadBatch, false, e.to_string())),
        })?;
        let shadow_maps = convert::shadow_maps_to_wire(&maps);
        let bytes: u64 = shadow_maps.iter().map(|m| m.encoded_len() as u64).sum();
        let scene_bytes = self.plan.scene_toml.len() + self.plan.headers.iter().map(|h| h.encoded_len()).sum::<usize>();
        let room = (trove_proto::MAX_MESSAGE_BYTES as u64).saturating_sub(scene_bytes as u64 + (1 << 16));
        if bytes > room {
            return Err(JobError::ShadowMaps { bytes, room });
        }
        self.scene_digest =
            convert::scene_digest(&self.plan.scene_toml, &self.plan.scene_name, &self.plan.headers, Some(&shadow_maps))
                .to_vec();
        self.shadow_maps = Some(shadow_maps);
        self.tally.stats.seconds.shadows += started.elapsed().as_secs_f64();
        Ok(())
    }
}

/// `open`'s factors from the first of `holders` that answers; a holder that is lost or busy
/// is passed over, one that refuses the scene fails the job.
async fn ask(
    holders: Vec<WorkerHandle>,
    open: pb::CastOpen,
    dataset: String,
) -> Result<(String, pb::ShadowReply), JobError> {
    for worker in holders {
        let mut client = WorkerClient::new(worker.channel.clone())
            .max_decoding_message_size(trove_proto::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(trove_proto::MAX_MESSAGE_BYTES);
        match client.shadow(pb::ShadowRequest { open: Some(open.clone()) }).await {
            Ok(reply) => return Ok((worker.id, reply.into_inner())),
            Err(status) => match convert::status_failure(&status) {
                Some(f) if !f.retryable => return Err(JobError::Worker { worker: worker.id, failure: Box::new(f) }),
                _ => tracing::warn!(worker = %worker.id, %status, "shadow request failed; trying another holder"),
            },
        }
    }
    Err(JobError::NoHolder { dataset })
}
