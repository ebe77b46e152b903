//! The shadow pass of a job whose scene has shadows (SPEC §6, trove-core `render::shadow`):
//! before any band, each dataset whose objects shade some lattice asks one of its holders
//! for their factors (`Shadow`), trying the next holder when one fails; the coordinator
//! multiplies them in object order (`ShadowPlan::combine`, as local mode does, so the maps
//! are the same f32s). A second round does the same for the fine points of the cells the
//! first round's maps refine (`ShadowPlan::refinement`, `ShadowPlan::refine`). The job's
//! streams then carry the maps with the scene.

use std::collections::HashSet;
use std::time::Instant;

use prost::Message;
use tokio::task::JoinSet;
use trove_core::render::shadow::{Factors, ShadowError, ShadowPlan};
use trove_core::scene::Scene;
use trove_proto::convert;
use trove_proto::v1 as pb;
use trove_proto::v1::worker_client::WorkerClient;

use super::super::registry::WorkerHandle;
use super::{Driver, JobError};

impl Driver {
    /// Computes the scene's shadow maps on the workers, when it has shadows: the lattices,
    /// then the fine points of their refined cells (`ShadowPlan::refinement`, a second round
    /// of requests carrying the first round's maps); from then on the streams carry the maps
    /// with the scene, and the scene's digest covers them.
    pub(super) async fn shadow_pass(&mut self) -> Result<(), JobError> {
        let scene = self.plan.scene.clone();
        let plan = ShadowPlan::of(&scene);
        if plan.is_empty() {
            return Ok(());
        }
        let started = Instant::now();
        let factors = self.shadow_factors(&scene, &plan, None).await?;
        let mut maps = plan.combine(&scene, factors).map_err(unfit)?;
        if plan.refines() {
            let first = scene.with_shadow_maps(maps.clone());
            let fine = plan.refinement(&first);
            if !fine.is_empty() {
                let factors = self.shadow_factors(&first, &fine, Some(convert::shadow_maps_to_wire(&maps))).await?;
                maps = fine.refine(&first, factors).map_err(unfit)?;
            }
        }
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

    /// One round of the shadow pass: the factors of `plan` from one holder of each dataset
    /// with work in it. `first_maps`, in the second round, are the first round's maps, which
    /// the requests carry (the workers derive the fine points from them).
    async fn shadow_factors(
        &mut self,
        scene: &Scene,
        plan: &ShadowPlan,
        first_maps: Option<Vec<pb::ShadowMap>>,
    ) -> Result<Vec<Factors>, JobError> {
        let refine = first_maps.is_some();
        let scene_digest = convert::scene_digest(
            &self.plan.scene_toml,
            &self.plan.scene_name,
            &self.plan.headers,
            first_maps.as_deref(),
        )
        .to_vec();
        let mut asks = JoinSet::new();
        // The scene (and the first round's maps) go once to each worker asked; its other
        // requests of the round name them by digest, as a job's cast streams do, so that a
        // scene of many datasets is not sent once per dataset.
        let mut carried: HashSet<String> = HashSet::new();
        for d in plan.datasets_with_work(scene) {
            let holders: Vec<WorkerHandle> = self
                .registry
                .holders(&self.plan.dataset_keys[d])
                .iter()
                .filter_map(|id| self.registry.handle(id))
                .collect();
            let full = pb::CastOpen {
                job_id: self.job.id.clone(),
                scene_toml: self.plan.scene_toml.clone(),
                scene_name: self.plan.scene_name.clone(),
                dataset: d as u32,
                headers: self.plan.headers.clone(),
                scene_digest: scene_digest.clone(),
                shadow_maps: first_maps.clone().unwrap_or_default(),
                shadow_maps_computed: refine,
            };
            let by_digest = pb::CastOpen {
                job_id: self.job.id.clone(),
                dataset: d as u32,
                scene_digest: scene_digest.clone(),
                shadow_maps_computed: refine,
                ..Default::default()
            };
            let digest_first = holders.first().is_some_and(|w| !carried.insert(w.id.clone()));
            let requests = Requests {
                full: pb::ShadowRequest { open: Some(full), refine },
                by_digest: pb::ShadowRequest { open: Some(by_digest), refine },
                digest_first,
            };
            let dataset = scene.datasets()[d].name().to_string();
            asks.spawn(ask(holders, requests, dataset));
        }
        let mut factors = Vec::new();
        while let Some(answer) = asks.join_next().await {
            let (worker, reply, sent) =
                answer.map_err(|e| JobError::Internal(format!("a shadow request failed: {e}")))??;
            self.tally.wire_to += sent;
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
        Ok(factors)
    }
}

/// Factors that passed each answer's checks but do not fit the plan together.
fn unfit(e: ShadowError) -> JobError {
    JobError::Worker {
        worker: "(a shadow answer)".into(),
        failure: Box::new(convert::failure(pb::Reason::BadBatch, false, e.to_string())),
    }
}

/// One dataset's request of a round, with the scene or naming it by digest.
struct Requests {
    full: pb::ShadowRequest,
    by_digest: pb::ShadowRequest,
    /// Whether the first holder was sent the scene by another request of the round.
    digest_first: bool,
}

/// The factors of `requests`' dataset from the first of `holders` that answers, and the
/// bytes sent for them; a holder that is lost or busy is passed over, one that refuses the
/// scene fails the job. A request by digest that the worker does not know the scene of (its
/// other request has not arrived yet, or it no longer holds the scene) goes again with it.
async fn ask(
    holders: Vec<WorkerHandle>,
    requests: Requests,
    dataset: String,
) -> Result<(String, pb::ShadowReply, u64), JobError> {
    let mut sent = 0u64;
    for (i, worker) in holders.into_iter().enumerate() {
        let mut client = WorkerClient::new(worker.channel.clone())
            .max_decoding_message_size(trove_proto::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(trove_proto::MAX_MESSAGE_BYTES);
        let mut request = if i == 0 && requests.digest_first { &requests.by_digest } else { &requests.full };
        loop {
            sent += request.encoded_len() as u64;
            match client.shadow(request.clone()).await {
                Ok(reply) => return Ok((worker.id, reply.into_inner(), sent)),
                Err(status) => match convert::status_failure(&status) {
                    Some(f) if f.reason() == pb::Reason::SceneUnknown && std::ptr::eq(request, &requests.by_digest) => {
                        request = &requests.full;
                        continue;
                    }
                    Some(f) if !f.retryable => {
                        return Err(JobError::Worker { worker: worker.id, failure: Box::new(f) });
                    }
                    _ => {
                        tracing::warn!(worker = %worker.id, %status, "shadow request failed; trying another holder");
                        break;
                    }
                },
            }
        }
    }
    Err(JobError::NoHolder { dataset })
}
