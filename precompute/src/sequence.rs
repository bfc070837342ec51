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
//!   first frame that computed them ([`crate::distances::DistanceCache`]): a later frame
//!   skips its paths (the voxel tracing of a non-convex object is most of S's time).
//! - **Resuming.** `OUT/.journal.json` records, per frame folder, a hash of what it was
//!   computed from. Running the same command again (after an interruption, or after editing
//!   some frames) precomputes only the frames whose hash is missing or changed.
//! - **Progress.** One line per frame through the observer (a server job) or on stderr.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

pub use translux_proto::animation::JOURNAL_FILE;
use translux_proto::animation::{
    SEQUENCE_FILE, SEQUENCE_FORMAT, SEQUENCE_VERSION, SequenceManifest,
};
use xxhash_rust::xxh3::Xxh3;

use crate::pipeline::{PrecomputeError, PrecomputeParams, precompute};
use crate::scene::{LoadedScene, SceneError, SceneSource, resolve_frame};

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

/// What [`precompute_sequence`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct SequenceReport {
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
    Folder {
        path: std::path::PathBuf,
        why: String,
    },
}

/// The name of frame `k`'s bundle folder.
pub fn frame_folder(k: u32) -> String {
    format!("frame-{k:04}")
}

/// Precomputes every frame of the animated scene `src` into `out` (see the module docs).
/// `on_frame` hears each frame as it is done.
pub fn precompute_sequence(
    src: &SceneSource,
    out: &Path,
    params: &PrecomputeParams,
    on_frame: &dyn Fn(&FrameReport, u32),
) -> Result<SequenceReport, SequenceError> {
    let t0 = Instant::now();
    src.file.validate().map_err(|error| {
        SequenceError::Scene(Box::new(SceneError::Invalid {
            scene: src.source.clone(),
            error,
        }))
    })?;
    let Some(anim) = src.file.animation else {
        return Err(SequenceError::Folder {
            path: out.to_path_buf(),
            why: "the scene is not animated (no `animation`): precompute it as one bundle".into(),
        });
    };
    prepare_folder(out)?;
    let journal_path = out.join(JOURNAL_FILE);
    let mut journal: BTreeMap<String, String> = std::fs::read(&journal_path)
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default();
    // A sequence being redone is not served half old, half new.
    remove_if_present(&out.join(SEQUENCE_FILE))?;

    // Every frame tells the same notes (an object turned outward, a mesh simplified): each
    // is told once, for the first frame that has it.
    let once = std::sync::Arc::new(OnceNotes {
        inner: params.observer.clone(),
        told: Default::default(),
    });
    // Objects that only move rigidly keep their optical distances from frame to frame.
    let params = &PrecomputeParams {
        observer: Some(once),
        distance_cache: Some(Default::default()),
        ..params.clone()
    };
    let settings = settings_key(params);
    let mut seen: BTreeMap<String, u32> = BTreeMap::new();
    let mut folders: Vec<String> = Vec::with_capacity(anim.frames as usize);
    let mut frames = Vec::with_capacity(anim.frames as usize);
    let mut bytes = 0u64;
    for k in 0..anim.frames {
        let t = Instant::now();
        let loaded = resolve_frame(
            &src.file,
            &src.base_dir,
            src.name.clone(),
            src.source.clone(),
            k,
        )
        .map_err(|error| SequenceError::FrameScene {
            frame: k,
            last: anim.frames - 1,
            error: Box::new(error),
        })?;
        let key = frame_key(&loaded, &settings);
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
            let kept = journal.get(&folder) == Some(&key)
                && dir.join(translux_proto::bundle::MANIFEST_FILE).is_file();
            let outcome = if kept {
                bytes += folder_bytes(&dir);
                FrameOutcome::Resumed
            } else {
                journal.remove(&folder);
                let r =
                    precompute(&loaded, &dir, params).map_err(|error| SequenceError::Frame {
                        frame: k,
                        error: Box::new(error),
                    })?;
                bytes += r.bundle_bytes;
                journal.insert(folder.clone(), key);
                write_json(&journal_path, &journal)?;
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
    // Frame folders of a longer or different earlier run that no frame uses now.
    let used: std::collections::BTreeSet<&String> = folders.iter().collect();
    if let Ok(entries) = std::fs::read_dir(out) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with("frame-") && !used.contains(&name) && e.path().is_dir() {
                let _ = std::fs::remove_dir_all(e.path());
                journal.remove(&name);
            }
        }
    }
    write_json(&journal_path, &journal)?;
    let manifest = SequenceManifest {
        format: SEQUENCE_FORMAT.into(),
        version: SEQUENCE_VERSION,
        name: src.name.clone(),
        fps: anim.fps,
        frames: folders,
    };
    write_json(&out.join(SEQUENCE_FILE), &manifest)?;
    Ok(SequenceReport {
        frames,
        bytes,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// An observer that passes each distinct note on once (to `inner`, or stderr without one)
/// and everything else through.
#[derive(Debug)]
struct OnceNotes {
    inner: Option<std::sync::Arc<dyn crate::pipeline::Observer>>,
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
/// `sequence.json`); a bundle or any other folder is refused, never overwritten.
fn prepare_folder(out: &Path) -> Result<(), SequenceError> {
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
    let mut entries = std::fs::read_dir(out).map_err(|e| err(format!("cannot read it: {e}")))?;
    if entries.next().is_some() {
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

/// Writes `value` as JSON to `path` atomically (a temporary file, then a rename).
fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<(), SequenceError> {
    let err = |why: String| SequenceError::Folder {
        path: path.to_path_buf(),
        why,
    };
    let text = serde_json::to_vec_pretty(value).map_err(|e| err(e.to_string()))?;
    let tmp = path.with_extension(format!("tmp-{}", std::process::id()));
    std::fs::write(&tmp, text).map_err(|e| err(format!("cannot write it: {e}")))?;
    std::fs::rename(&tmp, path).map_err(|e| err(format!("cannot write it: {e}")))
}
