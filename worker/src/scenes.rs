//! The scenes a worker casts for, parsed once and shared by their streams.
//!
//! A job opens one `Cast` stream per dataset on each worker that holds it, and every stream's
//! `open` carries the whole scene (its text and the headers of every file it names), so that
//! each stream can validate it on its own. Parsing it per stream made a job's work on a worker
//! grow with datasets × scene size: a scene of a thousand datasets was parsed a thousand
//! times, each time reading the headers of the worker's own files again. [`JobScenes`] keeps
//! the last few scenes parsed, keyed by what was parsed (text, name and headers, compared in
//! full, never by id alone: two coordinators may give different jobs the same id, and two
//! jobs of one scene share its parse), so each distinct scene is parsed once per worker
//! while it is in use.

use std::collections::HashMap;
use std::hash::{DefaultHasher, Hash, Hasher};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use trove_core::scene::Scene;
use trove_proto::v1 as pb;

/// Scenes kept at most: enough for the jobs of several coordinators interleaving their
/// streams on one worker, few enough that a scene's text and model (kilobytes to a few
/// megabytes) never add up to much beside the voxels.
pub const KEPT_SCENES: usize = 8;

/// What a scene's parse depends on: an `open` less its stream's own fields (job id, dataset).
#[derive(PartialEq, Eq, Hash)]
struct Parsed {
    scene_toml: String,
    scene_name: String,
    /// The headers' wire form: `pb::DatasetFile` is compared by value, not hashed.
    headers: Vec<u8>,
}

impl Parsed {
    fn of(open: &pb::CastOpen) -> Parsed {
        use prost::Message;
        let mut headers = Vec::new();
        for h in &open.headers {
            // Length-delimited, so that neighbouring headers cannot run together.
            h.encode_length_delimited(&mut headers).expect("a Vec grows as needed");
        }
        Parsed { scene_toml: open.scene_toml.clone(), scene_name: open.scene_name.clone(), headers }
    }

    fn digest(&self) -> u64 {
        let mut h = DefaultHasher::new();
        self.hash(&mut h);
        h.finish()
    }
}

struct Kept {
    parsed: Parsed,
    /// The scene once parsed. Streams of one scene opening at once wait here for the first
    /// one's parse instead of parsing it again; a failed parse leaves it empty.
    scene: Arc<Mutex<Option<Arc<Scene>>>>,
    /// When it was last asked for, on [`JobScenes`]'s own clock.
    used: u64,
}

#[derive(Default)]
struct Table {
    by_digest: HashMap<u64, Vec<Kept>>,
    clock: u64,
}

impl Table {
    fn len(&self) -> usize {
        self.by_digest.values().map(Vec::len).sum()
    }

    /// Drops the least recently used scene.
    fn evict_one(&mut self) {
        let oldest =
            self.by_digest.iter().flat_map(|(&d, v)| v.iter().enumerate().map(move |(i, k)| (k.used, d, i))).min();
        if let Some((_, digest, i)) = oldest {
            let bucket = self.by_digest.get_mut(&digest).expect("found above");
            bucket.swap_remove(i);
            if bucket.is_empty() {
                self.by_digest.remove(&digest);
            }
        }
    }
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
    /// The scene `open` carries: the one kept if the same text, name and headers were parsed
    /// before, else `parse()`'s, kept for the streams to come. Streams of one scene opening
    /// at once parse it once (the others wait for it). A failed parse is not kept: the next
    /// stream parses again, and fails the same way.
    pub fn get_or_parse<E>(
        &self,
        open: &pb::CastOpen,
        parse: impl FnOnce() -> Result<Scene, E>,
    ) -> Result<Arc<Scene>, E> {
        let cell = self.cell(Parsed::of(open));
        let mut cell = cell.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(scene) = cell.as_ref() {
            self.reused.fetch_add(1, Ordering::Relaxed);
            return Ok(scene.clone());
        }
        let scene = Arc::new(parse()?);
        self.parsed.fetch_add(1, Ordering::Relaxed);
        *cell = Some(scene.clone());
        Ok(scene)
    }

    /// The place of the scene `key` names, made (empty) if it is not kept, evicting the
    /// least recently used beyond [`KEPT_SCENES`].
    fn cell(&self, key: Parsed) -> Arc<Mutex<Option<Arc<Scene>>>> {
        let digest = key.digest();
        let mut table = self.table.lock().unwrap_or_else(|e| e.into_inner());
        table.clock += 1;
        let used = table.clock;
        if let Some(kept) = table.by_digest.get_mut(&digest).and_then(|b| b.iter_mut().find(|k| k.parsed == key)) {
            kept.used = used;
            return kept.scene.clone();
        }
        while table.len() >= KEPT_SCENES {
            table.evict_one();
        }
        let scene = Arc::new(Mutex::new(None));
        table.by_digest.entry(digest).or_default().push(Kept { parsed: key, scene: scene.clone(), used });
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
        }
    }

    #[test]
    fn each_scene_is_parsed_once_for_all_its_streams_and_jobs() {
        let scenes = JobScenes::default();
        let ok = |w| Ok::<_, ()>(scene(w));
        let a = scenes.get_or_parse(&open("a", 0, "job-1"), || ok(4)).unwrap();
        let b =
            scenes.get_or_parse(&open("a", 1, "job-1"), || -> Result<Scene, ()> { panic!("parsed again") }).unwrap();
        let c =
            scenes.get_or_parse(&open("a", 2, "job-2"), || -> Result<Scene, ()> { panic!("parsed again") }).unwrap();
        assert!(Arc::ptr_eq(&a, &b) && Arc::ptr_eq(&a, &c));
        assert_eq!((scenes.parsed(), scenes.reused()), (1, 2));
    }

    #[test]
    fn a_different_text_name_or_header_is_a_different_scene_even_under_one_job_id() {
        let scenes = JobScenes::default();
        let first = scenes.get_or_parse(&open("a", 0, "job-1"), || Ok::<_, ()>(scene(4))).unwrap();
        let other = scenes.get_or_parse(&open("b", 0, "job-1"), || Ok::<_, ()>(scene(8))).unwrap();
        assert_eq!(other.image().width, 8);
        let mut renamed = open("a", 0, "job-1");
        renamed.scene_name = "u.toml".into();
        scenes.get_or_parse(&renamed, || Ok::<_, ()>(scene(6))).unwrap();
        let mut headed = open("a", 0, "job-1");
        headed.headers.push(pb::DatasetFile { key: "x.raw".into(), bytes: 8, header: None });
        scenes.get_or_parse(&headed, || Ok::<_, ()>(scene(5))).unwrap();
        assert_eq!(scenes.parsed(), 4);
        assert_eq!(scenes.get_or_parse(&open("a", 3, "job-9"), || Ok::<_, ()>(scene(1))).unwrap().image().width, 4);
        assert!(!Arc::ptr_eq(&first, &other));
    }

    #[test]
    fn failures_are_not_kept_and_the_least_recently_used_scene_goes_first() {
        let scenes = JobScenes::default();
        assert_eq!(scenes.get_or_parse(&open("bad", 0, "j"), || Err::<Scene, _>("refused")).unwrap_err(), "refused");
        assert_eq!(scenes.get_or_parse(&open("bad", 1, "j"), || Err::<Scene, _>("again")).unwrap_err(), "again");
        for i in 0..KEPT_SCENES {
            scenes.get_or_parse(&open(&format!("s{i}"), 0, "j"), || Ok::<_, ()>(scene(4))).unwrap();
        }
        // s0 used again: s1 is now the oldest, and a new scene evicts it.
        scenes.get_or_parse(&open("s0", 1, "j"), || Err(())).unwrap();
        scenes.get_or_parse(&open("new", 0, "j"), || Ok::<_, ()>(scene(4))).unwrap();
        let parsed = scenes.parsed();
        scenes.get_or_parse(&open("s0", 2, "j"), || Err(())).unwrap();
        scenes.get_or_parse(&open("s1", 1, "j"), || Ok::<_, ()>(scene(4))).unwrap();
        assert_eq!(scenes.parsed(), parsed + 1, "s1 was evicted and parsed again; s0 was kept");
        assert_eq!(scenes.table.lock().unwrap().len(), KEPT_SCENES);
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
