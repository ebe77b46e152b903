//! The scenes a worker casts for, parsed once and shared by their streams.
//!
//! A job opens one `Cast` stream per dataset on each worker that holds it. Parsing the scene
//! per stream made a job's work on a worker grow with datasets × scene size: a scene of a
//! thousand datasets was parsed a thousand times, each time reading the headers of the
//! worker's own files again; and sending it per stream made the wire grow the same way.
//! [`JobScenes`] keeps the last few scenes parsed, keyed by their SHA-256
//! (`trove_proto::convert::scene_digest`, which the worker computes itself from what it
//! parses), so each distinct scene is parsed once per worker while it is kept — two jobs of
//! one scene share it — and the coordinator sends the scene only until a worker has accepted
//! one stream of the job: the other streams name it by digest alone. A digest this worker
//! does not hold (it restarted, or let the scene go) is refused as unknown, and the
//! coordinator opens that stream again with the scene.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use trove_core::scene::Scene;
use trove_proto::convert::scene_digest;
use trove_proto::v1 as pb;

/// Scenes kept at most: enough for the jobs of several coordinators interleaving their
/// streams on one worker, few enough that a scene's text and model (kilobytes to a few
/// megabytes) never add up to much beside the voxels.
pub const KEPT_SCENES: usize = 8;

/// A scene's SHA-256.
type Digest = [u8; 32];

/// A kept scene's place. Streams of one scene opening at once wait on it for the first one's
/// parse instead of parsing again; a failed parse leaves it empty.
type Cell = Arc<Mutex<Option<Arc<Scene>>>>;

struct Kept {
    scene: Cell,
    /// When it was last asked for, on [`JobScenes`]'s own clock.
    used: u64,
}

#[derive(Default)]
struct Table {
    by_digest: HashMap<Digest, Kept>,
    clock: u64,
}

/// Why an open found no scene.
#[derive(Debug, PartialEq, Eq)]
pub enum SceneRefusal<E> {
    /// It named its scene by a digest this worker does not hold.
    Unknown,
    /// It carried a digest other than its scene's: the two sides disagree on how a scene is
    /// named, and sending the scene again would not help.
    Mismatch,
    /// Parsing the scene it carried failed.
    Parse(E),
}

/// The last [`KEPT_SCENES`] scenes this worker parsed, and how often one was parsed or reused.
#[derive(Default)]
pub struct JobScenes {
    table: Mutex<Table>,
    parsed: AtomicU64,
    reused: AtomicU64,
}

impl std::fmt::Debug for JobScenes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("JobScenes").field("parsed", &self.parsed()).field("reused", &self.reused()).finish()
    }
}

impl JobScenes {
    /// The scene `open` names. An open that carries the scene gets the one kept under its
    /// digest if there is one, else `parse()`'s, kept for the streams to come; streams of one
    /// scene opening at once parse it once (the others wait for it), and a failed parse is
    /// not kept (the next stream parses again, and fails the same way). An open that carries
    /// only a digest gets the scene kept under it, or [`SceneRefusal::Unknown`].
    pub fn get_or_parse<E>(
        &self,
        open: &pb::CastOpen,
        parse: impl FnOnce() -> Result<Scene, E>,
    ) -> Result<Arc<Scene>, SceneRefusal<E>> {
        if open.scene_toml.is_empty() {
            let digest: Digest = open.scene_digest.as_slice().try_into().map_err(|_| SceneRefusal::Unknown)?;
            let cell = self.kept(&digest).ok_or(SceneRefusal::Unknown)?;
            let scene = cell.lock().unwrap_or_else(|e| e.into_inner()).clone().ok_or(SceneRefusal::Unknown)?;
            self.reused.fetch_add(1, Ordering::Relaxed);
            return Ok(scene);
        }
        let digest = scene_digest(
            &open.scene_toml,
            &open.scene_name,
            &open.headers,
            open.shadow_maps_computed.then_some(&open.shadow_maps[..]),
        );
        if !open.scene_digest.is_empty() && open.scene_digest[..] != digest[..] {
            return Err(SceneRefusal::Mismatch);
        }
        let cell = self.cell(digest);
        let mut cell = cell.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(scene) = cell.as_ref() {
            self.reused.fetch_add(1, Ordering::Relaxed);
            return Ok(scene.clone());
        }
        let scene = Arc::new(parse().map_err(SceneRefusal::Parse)?);
        self.parsed.fetch_add(1, Ordering::Relaxed);
        *cell = Some(scene.clone());
        Ok(scene)
    }

    /// The place kept under `digest`, marked used now.
    fn kept(&self, digest: &Digest) -> Option<Cell> {
        let mut table = self.table.lock().unwrap_or_else(|e| e.into_inner());
        table.clock += 1;
        let used = table.clock;
        let kept = table.by_digest.get_mut(digest)?;
        kept.used = used;
        Some(kept.scene.clone())
    }

    /// The place kept under `digest`, made (empty) if there is none, evicting the least
    /// recently used beyond [`KEPT_SCENES`].
    fn cell(&self, digest: Digest) -> Cell {
        let mut table = self.table.lock().unwrap_or_else(|e| e.into_inner());
        table.clock += 1;
        let used = table.clock;
        if let Some(kept) = table.by_digest.get_mut(&digest) {
            kept.used = used;
            return kept.scene.clone();
        }
        while table.by_digest.len() >= KEPT_SCENES {
            let oldest = table.by_digest.iter().min_by_key(|(_, k)| k.used).map(|(d, _)| *d);
            if let Some(d) = oldest {
                table.by_digest.remove(&d);
            }
        }
        let scene = Cell::default();
        table.by_digest.insert(digest, Kept { scene: scene.clone(), used });
        scene
    }

    /// Scenes parsed so far (one per distinct scene while it stays kept).
    pub fn parsed(&self) -> u64 {
        self.parsed.load(Ordering::Relaxed)
    }

    /// Streams that found their scene already parsed.
    pub fn reused(&self) -> u64 {
        self.reused.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(width: u32) -> Scene {
        let text = format!(
            "[image]\nwidth = {width}\nheight = 4\nbackground = [0, 0, 0]\n[camera]\neye = [0, 0, 5]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 30.0\n\
             [[datasets]]\nname = \"d\"\ndims = [2, 2, 2]\n[datasets.channels.voxel]\n\
             generator = {{ kind = \"constant\", value = 1.0 }}\n"
        );
        Scene::parse(&text, std::path::Path::new("t.toml")).expect("a valid scene")
    }

    fn open(text: &str, dataset: u32, job: &str) -> pb::CastOpen {
        pb::CastOpen {
            job_id: job.into(),
            scene_toml: text.into(),
            scene_name: "t.toml".into(),
            dataset,
            headers: vec![],
            scene_digest: scene_digest(text, "t.toml", &[], None).to_vec(),
            shadow_maps: vec![],
            shadow_maps_computed: false,
        }
    }

    /// An open naming `text`'s scene by digest alone.
    fn by_digest(text: &str, dataset: u32) -> pb::CastOpen {
        let digest = scene_digest(text, "t.toml", &[], None).to_vec();
        pb::CastOpen { dataset, scene_digest: digest, ..Default::default() }
    }

    fn never() -> Result<Scene, ()> {
        panic!("parsed again")
    }

    #[test]
    fn each_scene_is_parsed_once_for_all_its_streams_and_jobs() {
        let scenes = JobScenes::default();
        let a = scenes.get_or_parse(&open("a", 0, "job-1"), || Ok::<_, ()>(scene(4))).unwrap();
        let b = scenes.get_or_parse(&open("a", 1, "job-1"), never).unwrap();
        let c = scenes.get_or_parse(&open("a", 2, "job-2"), never).unwrap();
        let d = scenes.get_or_parse(&by_digest("a", 3), never).unwrap();
        assert!(Arc::ptr_eq(&a, &b) && Arc::ptr_eq(&a, &c) && Arc::ptr_eq(&a, &d));
        assert_eq!((scenes.parsed(), scenes.reused()), (1, 3));
    }

    #[test]
    fn a_digest_not_held_or_not_the_scenes_own_is_refused() {
        let scenes = JobScenes::default();
        assert_eq!(scenes.get_or_parse(&by_digest("a", 0), never).unwrap_err(), SceneRefusal::Unknown);
        let mut short = by_digest("a", 0);
        short.scene_digest.truncate(8);
        assert_eq!(scenes.get_or_parse(&short, never).unwrap_err(), SceneRefusal::Unknown);
        let mut wrong = open("a", 0, "j");
        wrong.scene_digest = scene_digest("b", "t.toml", &[], None).to_vec();
        assert_eq!(scenes.get_or_parse(&wrong, never).unwrap_err(), SceneRefusal::Mismatch);
        // A failed parse is not a scene held.
        assert_eq!(scenes.get_or_parse(&open("a", 0, "j"), || Err("bad")).unwrap_err(), SceneRefusal::Parse("bad"));
        assert_eq!(scenes.get_or_parse(&by_digest("a", 1), || Err("bad")).unwrap_err(), SceneRefusal::Unknown);
        // An open without a digest (an older coordinator's) is parsed and kept all the same.
        let mut plain = open("a", 0, "j");
        plain.scene_digest.clear();
        scenes.get_or_parse(&plain, || Ok::<_, ()>(scene(4))).unwrap();
        scenes.get_or_parse(&by_digest("a", 1), never).unwrap();
    }

    #[test]
    fn a_different_text_name_or_header_is_a_different_scene_even_under_one_job_id() {
        let scenes = JobScenes::default();
        let first = scenes.get_or_parse(&open("a", 0, "job-1"), || Ok::<_, ()>(scene(4))).unwrap();
        let other = scenes.get_or_parse(&open("b", 0, "job-1"), || Ok::<_, ()>(scene(8))).unwrap();
        assert_eq!(other.image().width, 8);
        let mut renamed = open("a", 0, "job-1");
        renamed.scene_name = "u.toml".into();
        renamed.scene_digest.clear();
        scenes.get_or_parse(&renamed, || Ok::<_, ()>(scene(6))).unwrap();
        let mut headed = open("a", 0, "job-1");
        headed.headers.push(pb::DatasetFile { key: "x.raw".into(), bytes: 8, header: None });
        headed.scene_digest.clear();
        scenes.get_or_parse(&headed, || Ok::<_, ()>(scene(5))).unwrap();
        assert_eq!(scenes.parsed(), 4);
        assert_eq!(scenes.get_or_parse(&open("a", 3, "job-9"), never).unwrap().image().width, 4);
        assert!(!Arc::ptr_eq(&first, &other));
    }

    #[test]
    fn the_least_recently_used_scene_goes_first() {
        let scenes = JobScenes::default();
        for i in 0..KEPT_SCENES {
            scenes.get_or_parse(&open(&format!("s{i}"), 0, "j"), || Ok::<_, ()>(scene(4))).unwrap();
        }
        // s0 used again: s1 is now the oldest, and a new scene evicts it.
        scenes.get_or_parse(&by_digest("s0", 1), never).unwrap();
        scenes.get_or_parse(&open("new", 0, "j"), || Ok::<_, ()>(scene(4))).unwrap();
        assert_eq!(scenes.get_or_parse(&by_digest("s1", 1), never).unwrap_err(), SceneRefusal::Unknown);
        let parsed = scenes.parsed();
        scenes.get_or_parse(&open("s0", 2, "j"), never).unwrap();
        scenes.get_or_parse(&open("s1", 1, "j"), || Ok::<_, ()>(scene(4))).unwrap();
        assert_eq!(scenes.parsed(), parsed + 1, "s1 was evicted and parsed again; s0 was kept");
        assert_eq!(scenes.table.lock().unwrap().by_digest.len(), KEPT_SCENES);
    }

    #[test]
    fn streams_opening_one_scene_at_once_parse_it_once() {
        let scenes = JobScenes::default();
        let barrier = std::sync::Barrier::new(8);
        std::thread::scope(|s| {
            for d in 0..8 {
                let (scenes, barrier) = (&scenes, &barrier);
                s.spawn(move || {
                    barrier.wait();
                    scenes
                        .get_or_parse(&open("a", d, "j"), || {
                            std::thread::sleep(std::time::Duration::from_millis(20));
                            Ok::<_, ()>(scene(4))
                        })
                        .unwrap();
                });
            }
        });
        assert_eq!((scenes.parsed(), scenes.reused()), (1, 7));
    }
}
