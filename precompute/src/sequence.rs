//! Animated scenes: one bundle per frame, and `sequence.json` beside them.
//!
//! In: a parsed scene with `animation` ([`crate::scene::SceneSource`]), an output folder and
//! the usual [`PrecomputeParams`]. Out: `OUT/frame-0000/`, `OUT/frame-0001/`, … (each a whole
//! bundle, written atomically by [`crate::pipeline::precompute`]) and `OUT/sequence.json`
//! ([`SequenceManifest`]), written last: a folder without it is not a sequence yet and the
//! server does not serve it.
//!
//! - **Sharing.** A frame whose resolved scene (triangles, materials, lights, settings) is the
//!   same as an earlier frame's — a held pose, a pause — points at that frame's folder
//!   instead of precomputing again.
//! - **Rigid objects.** A homogeneous translucent object that only moves rigidly (keyframes
//!   that translate and turn it) keeps the optical distances between its patches from the
//!   first frame of its block that computed them ([`crate::distances::DistanceCache`]): a
//!   later frame skips its paths (the voxel tracing of a non-convex object is most of S's
//!   time). The cache starts empty at every block of [`BLOCK_FRAMES`] frames (frames 0–7,
//!   8–15, …), whether the sequence runs on one box or in shards: a frame's bundle then
//!   depends only on the frames of its own block, so any split gives the same bytes.
//! - **Resuming.** Beside each frame folder, a record `.frame-NNNN.key` holds a hash of what
//!   it was computed from (the frame's scene and the settings). It is removed before the
//!   frame is computed again and written after its bundle is in place, so a record is only
//!   ever beside the bundle it describes. Running the same command again (after an
//!   interruption, or after editing some frames) precomputes only the frames whose record is
//!   missing or different. `OUT/.journal.json` marks the folder as a sequence being made
//!   (the server says "not finished" for a folder with it and without `sequence.json`); a
//!   whole run and a merge also list the records there, for people — nothing reads it back.
//!   (A frame computed again after a resume takes no optical distances from the frames of
//!   its block that were kept: it traces its own, as valid, not always the same bytes.)
//! - **Shards** ([`precompute_sequence_shard`], `--shard I/K`). Shard I of K precomputes a
//!   share of consecutive blocks ([`shard_frames`]): consecutive frames keep the rigid
//!   objects' distances within the shard (round robin would give each shard frames far
//!   apart, every one tracing its own) and a held pose next to the frame it holds is shared
//!   in the same shard. Each frame is the whole bundle and record a one-box run makes;
//!   shards write only their own frames' folders and records — no file is written by two
//!   shards (`.journal.json` is only created when absent) — and never `sequence.json` (a
//!   shard removes it: the sequence is being redone). A shard reads the scene of every
//!   earlier frame (meshes only, no precompute) to know which frames are held poses: a
//!   frame the same as an earlier frame of another share points at that frame's folder, as
//!   on one box, and is not computed. Running a finished shard again keeps every frame.
//! - **Merge** ([`merge_sequence`], `--merge K`): every distinct frame's folder must be
//!   there with the record of the current inputs; a missing or stale one is refused, named
//!   with the `--shard I/K` command that makes it. Then the frame folders that no frame uses
//!   are removed and `sequence.json` is written, last and atomically. As the frames do not
//!   depend on the split, the merged folder is what one box makes (the bundles' arrays byte
//!   for byte), whatever K the shards ran with.
//! - **Progress.** One line per frame through the observer (a server job) or on stderr.

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

pub use translux_proto::animation::JOURNAL_FILE;
use translux_proto::animation::{
    Animation, SEQUENCE_FILE, SEQUENCE_FORMAT, SEQUENCE_VERSION, SequenceManifest,
};
use translux_proto::bundle::MANIFEST_FILE;
use xxhash_rust::xxh3::Xxh3;

use crate::distances::DistanceCache;
use crate::pipeline::{PrecomputeError, PrecomputeParams, precompute};
use crate::scene::{LoadedScene, SceneError, SceneSource, resolve_frame};
use crate::shard::Shard;

/// Frames per block: the optical distances of rigidly moving objects are kept within a
/// block, and shards take whole blocks (see the module docs).
pub const BLOCK_FRAMES: u32 = 8;

/// The frames shard `shard` precomputes of a sequence of `frames`: the consecutive blocks
/// of [`BLOCK_FRAMES`] that [`Shard::rows`] gives it among all the blocks (empty when there
/// are fewer blocks than shards).
pub fn shard_frames(frames: u32, shard: Shard) -> Range<u32> {
    let blocks = frames.div_ceil(BLOCK_FRAMES);
    let b = shard.rows(blocks as usize);
    let at = |block: usize| (block as u32).saturating_mul(BLOCK_FRAMES).min(frames);
    at(b.start)..at(b.end)
}

/// The shard of a split into `count` that precomputes frame `frame` of `frames`.
pub fn shard_of_frame(frames: u32, frame: u32, count: u32) -> Shard {
    (0..count)
        .map(|index| Shard { index, count })
        .find(|s| shard_frames(frames, *s).contains(&frame))
        .unwrap_or(Shard {
            index: count.saturating_sub(1),
            count,
        })
}

/// What happened to one frame.
#[derive(Debug, Clone, PartialEq)]
pub enum FrameOutcome {
    /// Precomputed now: its patch count and bundle bytes.
    Computed { patches: usize, bytes: u64 },
    /// Its bundle from an earlier run was kept (same inputs).
    Resumed,
    /// The same scene as this earlier frame: it shares that frame's bundle.
    SharedWith(u32),
}

/// One frame of a [`SequenceReport`].
#[derive(Debug, Clone, PartialEq)]
pub struct FrameReport {
    pub frame: u32,
    /// Its bundle folder (relative to the sequence folder).
    pub folder: String,
    pub outcome: FrameOutcome,
    /// Loading its meshes and (when computed) its precompute, s.
    pub seconds: f64,
}

/// What [`precompute_sequence`] (or a shard of it, or a merge) did.
#[derive(Debug, Clone, PartialEq)]
pub struct SequenceReport {
    /// The frames of this run: every frame, or a shard's.
    pub frames: Vec<FrameReport>,
    /// Bytes of every distinct frame bundle.
    pub bytes: u64,
    pub seconds: f64,
}

impl SequenceReport {
    /// Frames precomputed now.
    pub fn computed(&self) -> usize {
        self.count(|o| matches!(o, FrameOutcome::Computed { .. }))
    }

    /// Frames kept from an earlier run.
    pub fn resumed(&self) -> usize {
        self.count(|o| matches!(o, FrameOutcome::Resumed))
    }

    /// Frames sharing an earlier frame's bundle.
    pub fn shared(&self) -> usize {
        self.count(|o| matches!(o, FrameOutcome::SharedWith(_)))
    }

    /// Mean and longest time of the frames precomputed now, s (`None` if none was).
    pub fn seconds_per_frame(&self) -> Option<(f64, f64)> {
        let s: Vec<f64> = self
            .frames
            .iter()
            .filter(|f| matches!(f.outcome, FrameOutcome::Computed { .. }))
            .map(|f| f.seconds)
            .collect();
        let mean = s.iter().sum::<f64>() / s.len().max(1) as f64;
        (!s.is_empty()).then(|| (mean, s.iter().fold(0.0f64, |m, v| m.max(*v))))
    }

    fn count(&self, f: impl Fn(&FrameOutcome) -> bool) -> usize {
        self.frames.iter().filter(|r| f(&r.outcome)).count()
    }
}

/// Why a sequence stopped; frames finished before it stay (a rerun resumes after them).
#[derive(Debug, thiserror::Error)]
pub enum SequenceError {
    #[error("{0}")]
    Scene(Box<SceneError>),
    #[error("frame {frame} (of frames 0 to {last}): {error}")]
    FrameScene {
        frame: u32,
        last: u32,
        #[source]
        error: Box<SceneError>,
    },
    #[error("frame {frame}: {error}")]
    Frame {
        frame: u32,
        #[source]
        error: Box<PrecomputeError>,
    },
    #[error("{}: {why}", .path.display())]
    Folder { path: PathBuf, why: String },
    /// A merge found frames missing or made from other inputs (each named with the shard
    /// command that makes it).
    #[error("{0}")]
    Unfinished(String),
}

/// The name of frame `k`'s bundle folder.
pub fn frame_folder(k: u32) -> String {
    format!("frame-{k:04}")
}

/// The record beside frame folder `folder`: the hash of what it was computed from.
fn record_path(out: &Path, folder: &str) -> PathBuf {
    out.join(format!(".{folder}.key"))
}

/// The hash in a frame's record, if it has one.
fn read_record(out: &Path, folder: &str) -> Option<String> {
    std::fs::read_to_string(record_path(out, folder))
        .ok()
        .map(|s| s.trim().to_string())
}

/// Precomputes every frame of the animated scene `src` into `out` (see the module docs).
/// `on_frame` hears each frame as it is done.
pub fn precompute_sequence(
    src: &SceneSource,
    out: &Path,
    params: &PrecomputeParams,
    on_frame: &dyn Fn(&FrameReport, u32),
) -> Result<SequenceReport, SequenceError> {
    run_frames(src, out, params, None, on_frame)
}

/// Precomputes the frames of shard `shard` ([`shard_frames`]) of the animated scene `src`
/// into `out`, each a whole bundle with its record, and no `sequence.json` (the merge
/// writes it). Frames kept from an earlier run with the same inputs are not computed again.
/// `on_frame` hears each of the shard's frames as it is done.
pub fn precompute_sequence_shard(
    src: &SceneSource,
    out: &Path,
    params: &PrecomputeParams,
    shard: Shard,
    on_frame: &dyn Fn(&FrameReport, u32),
) -> Result<SequenceReport, SequenceError> {
    run_frames(src, out, params, Some(shard), on_frame)
}

/// The scene's animation, after checking the scene file.
fn animation_of(src: &SceneSource, out: &Path) -> Result<Animation, SequenceError> {
    src.file.validate().map_err(|error| {
        SequenceError::Scene(Box::new(SceneError::Invalid {
            scene: src.source.clone(),
            error,
        }))
    })?;
    src.file.animation.ok_or_else(|| SequenceError::Folder {
        path: out.to_path_buf(),
        why: "the scene is not animated (no `animation`): precompute it as one bundle".into(),
    })
}

/// Frame `k` of `src`, resolved (its meshes loaded, keyframes applied).
fn load_frame(src: &SceneSource, k: u32, frames: u32) -> Result<LoadedScene, SequenceError> {
    resolve_frame(
        &src.file,
        &src.base_dir,
        src.name.clone(),
        src.source.clone(),
        k,
    )
    .map_err(|error| SequenceError::FrameScene {
        frame: k,
        last: frames - 1,
        error: Box::new(error),
    })
}

/// The frames of the whole sequence (`shard: None`) or of one shard: see the module docs.
fn run_frames(
    src: &SceneSource,
    out: &Path,
    params: &PrecomputeParams,
    shard: Option<Shard>,
    on_frame: &dyn Fn(&FrameReport, u32),
) -> Result<SequenceReport, SequenceError> {
    let t0 = Instant::now();
    let anim = animation_of(src, out)?;
    let range = shard.map_or(0..anim.frames, |s| shard_frames(anim.frames, s));
    if range.is_empty() {
        // More shards than blocks: this one has nothing to do (and touches nothing).
        return Ok(SequenceReport {
            frames: Vec::new(),
            bytes: 0,
            seconds: t0.elapsed().as_secs_f64(),
        });
    }
    prepare_folder(out, shard.is_some())?;
    if shard.is_some() && !out.join(JOURNAL_FILE).is_file() {
        // The marker only: every shard's records are files of their own. Shards starting
        // together may all write it; any one of them standing is enough.
        let written = write_atomic(&out.join(JOURNAL_FILE), b"{}\n");
        if !out.join(JOURNAL_FILE).is_file() {
            written?;
        }
    }
    // A sequence being redone is not served half old, half new.
    remove_if_present(&out.join(SEQUENCE_FILE))?;

    // Every frame tells the same notes (an object turned outward, a mesh simplified): each
    // is told once, for the first frame that has it.
    let once = Arc::new(OnceNotes {
        inner: params.observer.clone(),
        told: Default::default(),
    });
    let params = &PrecomputeParams {
        observer: Some(once),
        ..params.clone()
    };
    let settings = settings_key(params);
    let mut seen: BTreeMap<String, u32> = BTreeMap::new();
    // Every frame's folder up to the end of the range (earlier shares' frames included).
    let mut folders: Vec<String> = Vec::with_capacity(range.end as usize);
    let mut frames = Vec::with_capacity(range.len());
    let mut bytes = 0u64;
    // Objects that only move rigidly keep their optical distances within a block.
    let mut cache = Arc::new(DistanceCache::default());
    for k in 0..range.end {
        let t = Instant::now();
        let loaded = load_frame(src, k, anim.frames)?;
        let key = frame_key(&loaded, &settings);
        if k < range.start {
            // Another share's frame: only which frames it holds the pose of.
            let first = *seen.entry(key).or_insert(k);
            folders.push(frame_folder(first));
            continue;
        }
        if k.is_multiple_of(BLOCK_FRAMES) {
            cache = Arc::new(DistanceCache::default());
        }
        let report = if let Some(&first) = seen.get(&key) {
            let folder = folders[first as usize].clone();
            folders.push(folder.clone());
            FrameReport {
                frame: k,
                folder,
                outcome: FrameOutcome::SharedWith(first),
                seconds: t.elapsed().as_secs_f64(),
            }
        } else {
            seen.insert(key.clone(), k);
            let folder = frame_folder(k);
            let dir = out.join(&folder);
            let kept = read_record(out, &folder).as_ref() == Some(&key)
                && dir.join(MANIFEST_FILE).is_file();
            let outcome = if kept {
                bytes += folder_bytes(&dir);
                FrameOutcome::Resumed
            } else {
                // No record while the folder is being replaced: a killed run leaves the
                // frame to be computed again.
                remove_if_present(&record_path(out, &folder))?;
                let frame_params = PrecomputeParams {
                    distance_cache: Some(cache.clone()),
                    ..params.clone()
                };
                let r = precompute(&loaded, &dir, &frame_params).map_err(|error| {
                    SequenceError::Frame {
                        frame: k,
                        error: Box::new(error),
                    }
                })?;
                bytes += r.bundle_bytes;
                write_atomic(&record_path(out, &folder), format!("{key}\n").as_bytes())?;
                FrameOutcome::Computed {
                    patches: r.patch_count,
                    bytes: r.bundle_bytes,
                }
            };
            folders.push(folder.clone());
            FrameReport {
                frame: k,
                folder,
                outcome,
                seconds: t.elapsed().as_secs_f64(),
            }
        };
        on_frame(&report, anim.frames);
        frames.push(report);
    }
    match shard {
        Some(_) => {
            // Folders of this share's frames that no frame uses now (a pose held since):
            // only this share's, so parallel shards never touch each other's.
            let used: std::collections::BTreeSet<String> =
                folders[range.start as usize..].iter().cloned().collect();
            for k in range {
                let folder = frame_folder(k);
                if !used.contains(&folder) {
                    remove_frame(out, &folder);
                }
            }
        }
        None => finish(src, out, &anim, folders)?,
    }
    Ok(SequenceReport {
        frames,
        bytes,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// A frame folder and its record, gone.
fn remove_frame(out: &Path, folder: &str) {
    let dir = out.join(folder);
    if dir.is_dir() {
        let _ = std::fs::remove_dir_all(&dir);
    }
    let _ = std::fs::remove_file(record_path(out, folder));
}

/// The end of a whole run or a merge: the frame folders no frame uses (and their records)
/// removed, `.journal.json` listing the records, then `sequence.json`.
fn finish(
    src: &SceneSource,
    out: &Path,
    anim: &Animation,
    folders: Vec<String>,
) -> Result<(), SequenceError> {
    let used: std::collections::BTreeSet<&String> = folders.iter().collect();
    if let Ok(entries) = std::fs::read_dir(out) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let folder = name
                .strip_prefix('.')
                .and_then(|n| n.strip_suffix(".key"))
                .unwrap_or(&name)
                .to_string();
            if folder.starts_with("frame-") && !used.contains(&folder) {
                remove_frame(out, &folder);
            }
        }
    }
    let journal: BTreeMap<&String, String> = used
        .iter()
        .filter_map(|f| read_record(out, f).map(|k| (*f, k)))
        .collect();
    write_json(&out.join(JOURNAL_FILE), &journal)?;
    let manifest = SequenceManifest {
        format: SEQUENCE_FORMAT.into(),
        version: SEQUENCE_VERSION,
        name: src.name.clone(),
        fps: anim.fps,
        frames: folders,
    };
    write_json(&out.join(SEQUENCE_FILE), &manifest)
}

/// Puts the frames the shards of a split into `count` precomputed in `out` together: every
/// distinct frame's bundle must be there with the record of its current inputs (`params`
/// as the shards had them); a missing or stale one is refused, named with the command
/// `rerun` gives for its shard. Then finishes the sequence as a whole run does
/// (`sequence.json` last). Every frame is reported kept or shared.
pub fn merge_sequence(
    src: &SceneSource,
    out: &Path,
    params: &PrecomputeParams,
    count: u32,
    rerun: &dyn Fn(Shard) -> String,
) -> Result<SequenceReport, SequenceError> {
    let t0 = Instant::now();
    let anim = animation_of(src, out)?;
    if out.exists() {
        prepare_folder(out, true)?;
    }
    let settings = settings_key(params);
    let mut seen: BTreeMap<String, u32> = BTreeMap::new();
    let mut folders: Vec<String> = Vec::with_capacity(anim.frames as usize);
    let mut frames = Vec::with_capacity(anim.frames as usize);
    let mut bytes = 0u64;
    // (frame, folder, why) of every frame not ready.
    let mut problems: Vec<(u32, String, &str)> = Vec::new();
    for k in 0..anim.frames {
        let t = Instant::now();
        let key = frame_key(&load_frame(src, k, anim.frames)?, &settings);
        let (folder, outcome) = match seen.get(&key) {
            Some(&first) => (
                folders[first as usize].clone(),
                FrameOutcome::SharedWith(first),
            ),
            None => {
                seen.insert(key.clone(), k);
                let folder = frame_folder(k);
                let dir = out.join(&folder);
                let record = read_record(out, &folder);
                if !dir.join(MANIFEST_FILE).is_file() || record.is_none() {
                    problems.push((k, folder.clone(), "missing"));
                } else if record.as_ref() != Some(&key) {
                    problems.push((
                        k,
                        folder.clone(),
                        "made from other inputs (the scene, its meshes or the settings \
                         changed since)",
                    ));
                } else {
                    bytes += folder_bytes(&dir);
                }
                (folder, FrameOutcome::Resumed)
            }
        };
        folders.push(folder.clone());
        frames.push(FrameReport {
            frame: k,
            folder,
            outcome,
            seconds: t.elapsed().as_secs_f64(),
        });
    }
    if !problems.is_empty() {
        let why = unfinished(out, &anim, (count, seen.len()), &problems, rerun);
        return Err(SequenceError::Unfinished(why));
    }
    finish(src, out, &anim, folders)?;
    Ok(SequenceReport {
        frames,
        bytes,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// The merge's refusal: each frame not ready (the first few), then the command of each
/// shard that makes them.
fn unfinished(
    out: &Path,
    anim: &Animation,
    (count, distinct): (u32, usize),
    problems: &[(u32, String, &str)],
    rerun: &dyn Fn(Shard) -> String,
) -> String {
    const LISTED: usize = 12;
    let mut text = format!(
        "{} of the {distinct} frame bundles in {} are missing or stale, so the sequence is \
         not written:",
        problems.len(),
        out.display()
    );
    for (k, folder, why) in problems.iter().take(LISTED) {
        let shard = shard_of_frame(anim.frames, *k, count);
        text += &format!("\n  frame {k} ({folder}) is {why}: shard {shard}");
    }
    if problems.len() > LISTED {
        text += &format!("\n  … and {} more", problems.len() - LISTED);
    }
    let mut shards: Vec<Shard> = problems
        .iter()
        .map(|p| shard_of_frame(anim.frames, p.0, count))
        .collect();
    shards.dedup();
    text += "\nrun (then merge again):";
    for s in shards {
        text += &format!("\n  {}", rerun(s));
    }
    text
}

/// An observer that passes each distinct note on once (to `inner`, or stderr without one)
/// and everything else through.
#[derive(Debug)]
struct OnceNotes {
    inner: Option<Arc<dyn crate::pipeline::Observer>>,
    told: std::sync::Mutex<std::collections::BTreeSet<String>>,
}

impl crate::pipeline::Observer for OnceNotes {
    fn progress(&self, stage: &str, done: u64, total: u64) {
        if let Some(o) = &self.inner {
            o.progress(stage, done, total);
        }
    }

    fn cancelled(&self) -> bool {
        self.inner.as_ref().is_some_and(|o| o.cancelled())
    }

    fn note(&self, message: &str) {
        let new = self
            .told
            .lock()
            .map(|mut t| t.insert(message.to_string()))
            .unwrap_or(true);
        if new {
            match &self.inner {
                Some(o) => o.note(message),
                None => eprintln!("{message}"),
            }
        }
    }
}

/// `out` must be a new folder, an empty one or an earlier sequence (its journal or its
/// `sequence.json`); a bundle or any other folder is refused, never overwritten. With
/// `shared` (a shard, a merge), also a folder other shards are filling: nothing in it but
/// frame folders and hidden files (a shard that started a moment earlier may not have
/// written the journal yet).
fn prepare_folder(out: &Path, shared: bool) -> Result<(), SequenceError> {
    let err = |why: String| SequenceError::Folder {
        path: out.to_path_buf(),
        why,
    };
    if !out.exists() {
        return std::fs::create_dir_all(out).map_err(|e| err(format!("cannot create it: {e}")));
    }
    if !out.is_dir() {
        return Err(err("exists and is not a folder".into()));
    }
    if out.join(JOURNAL_FILE).is_file() || out.join(SEQUENCE_FILE).is_file() {
        return Ok(());
    }
    let entries = std::fs::read_dir(out).map_err(|e| err(format!("cannot read it: {e}")))?;
    let mut names = entries
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned());
    let fits = |n: &String| shared && (n.starts_with('.') || n.starts_with("frame-"));
    if names.any(|n| !fits(&n)) {
        return Err(err(
            "exists and is not a sequence folder (no sequence.json or .journal.json): an \
             animated scene writes one bundle per frame there; choose a new or empty folder"
                .into(),
        ));
    }
    Ok(())
}

/// Everything but the scene that decides a frame's bundle.
fn settings_key(p: &PrecomputeParams) -> String {
    format!(
        "{:?}|{:?}|{:?}|{:?}|{:?}|{:?}|{:?}|{:?}|{:?}|{}",
        p.patches,
        p.max_edge,
        p.form_factors,
        p.transport,
        p.subsurface,
        p.voxels,
        p.inverse,
        p.environment,
        p.subsurface_links,
        env!("CARGO_PKG_VERSION"),
    )
}

/// A hash of frame `s` as it will be precomputed: its file (materials, lights, camera,
/// patches) and every triangle, bit for bit, with the `settings`.
fn frame_key(s: &LoadedScene, settings: &str) -> String {
    let mut h = Xxh3::new();
    h.update(settings.as_bytes());
    // Mesh paths differ between frames that may still be the same scene: hash the triangles
    // instead of the paths.
    let mut file = s.file.clone();
    for o in &mut file.objects {
        if let translux_proto::scene::MeshRef::Path(p) = &mut o.mesh {
            p.clear();
        }
        o.transform = None;
    }
    h.update(&serde_json::to_vec(&file).unwrap_or_default());
    for o in &s.objects {
        h.update(&(o.triangles.len() as u64).to_le_bytes());
        for t in &o.triangles {
            for v in t {
                for c in v.to_array() {
                    h.update(&c.to_bits().to_le_bytes());
                }
            }
        }
        h.update(&[o.reoriented as u8]);
        if let Some(f) = &o.face_material {
            h.update(bytemuck::cast_slice(f));
        }
    }
    format!("{:032x}", h.digest128())
}

fn folder_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .map(|es| {
            es.flatten()
                .filter_map(|e| e.metadata().ok())
                .filter(|m| m.is_file())
                .map(|m| m.len())
                .sum()
        })
        .unwrap_or(0)
}

fn remove_if_present(path: &Path) -> Result<(), SequenceError> {
    match std::fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(SequenceError::Folder {
            path: path.to_path_buf(),
            why: format!("cannot remove it: {e}"),
        }),
    }
}

/// Writes `value` as JSON to `path` atomically ([`write_atomic`]).
fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<(), SequenceError> {
    let text = serde_json::to_vec_pretty(value).map_err(|e| SequenceError::Folder {
        path: path.to_path_buf(),
        why: e.to_string(),
    })?;
    write_atomic(path, &text)
}

/// Writes `bytes` to `path` atomically: a temporary file beside it (`NAME.tmp-PID-NANOS`:
/// shards on other machines may have the same process id), then a rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), SequenceError> {
    let err = |why: String| SequenceError::Folder {
        path: path.to_path_buf(),
        why,
    };
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(
        ".tmp-{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos())
    ));
    let tmp = path.with_file_name(name);
    std::fs::write(&tmp, bytes).map_err(|e| err(format!("cannot write it: {e}")))?;
    std::fs::rename(&tmp, path).map_err(|e| err(format!("cannot write it: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_take_consecutive_whole_blocks_of_every_frame() {
        for frames in [1, 7, 8, 9, 20, 100] {
            for count in [1, 2, 3, 5, 16] {
                let mut next = 0;
                for index in 0..count {
                    let s = Shard { index, count };
                    let r = shard_frames(frames, s);
                    assert_eq!(r.start, next, "{frames} frames, {s}");
                    assert!(r.start.is_multiple_of(BLOCK_FRAMES) || r.is_empty());
                    for k in r.clone() {
                        assert_eq!(shard_of_frame(frames, k, count), s);
                    }
                    next = r.end.max(next);
                }
                assert_eq!(next, frames, "{frames} frames in {count}");
            }
        }
        assert_eq!(shard_frames(20, Shard { index: 1, count: 2 }), 8..20);
        assert!(shard_frames(9, Shard { index: 0, count: 3 }).is_empty());
    }
}
