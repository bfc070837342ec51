//! Animated scenes: a scene file's `animation` (frame count and rate), an object's
//! per-frame mesh files and keyframed transforms, and the `sequence.json` that
//! `translux-precompute` writes beside one bundle per frame.
//!
//! In: a scene file (`scene::SceneFile`) with `animation` set. Out: for frame k, the static scene
//! of that frame ([`frame_mesh_path`], [`Keyframe::at`]); after the precompute, a
//! [`SequenceManifest`] naming each frame's bundle folder.
//!
//! ```json
//! {
//!   "animation": {"frames": 48, "fps": 24, "first_number": 1},
//!   "objects": [
//!     {"name": "horse", "mesh": "gallop/horse_{frame:02}.obj", ...},
//!     {"name": "ball", "mesh": {"shape": "sphere", "radius": 0.1},
//!      "keyframes": [{"frame": 0, "translate": [-1, 0.1, 0]},
//!                    {"frame": 47, "translate": [1, 0.1, 0], "rotate_deg": [0, 0, -360]}], ...}
//!   ]
//! }
//! ```

use serde::{Deserialize, Serialize};

use crate::transform::{Scale, Transform};
use crate::validate::{FieldError, check_finite, check_vec_finite};

/// The most frames a scene may have (a minute at 60 fps and then some).
pub const MAX_FRAMES: u32 = 10_000;

/// The file beside the frame bundles that makes a folder a sequence.
pub const SEQUENCE_FILE: &str = "sequence.json";
/// The journal beside the frame bundles while (and after) a sequence is precomputed: per
/// frame folder, a hash of what it was computed from (how a rerun resumes).
pub const JOURNAL_FILE: &str = ".journal.json";
/// [`SequenceManifest::format`].
pub const SEQUENCE_FORMAT: &str = "translux-sequence";
/// [`SequenceManifest::version`].
pub const SEQUENCE_VERSION: u32 = 1;

fn default_fps() -> f32 {
    24.0
}

/// A scene file's `animation`: it has `frames` frames, frame k shown at time k / `fps`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Animation {
    /// Number of frames (1 to [`MAX_FRAMES`]); frames are numbered 0 to `frames` − 1 in
    /// keyframes and in the API.
    pub frames: u32,
    /// Playback rate in frames per second (default 24).
    #[serde(default = "default_fps")]
    pub fps: f32,
    /// The number frame 0's mesh files carry in `{frame}` patterns (default 0; 1 for
    /// exporters that count from 1): frame k reads file number `first_number + k`.
    #[serde(default)]
    pub first_number: u32,
}

impl Animation {
    /// Checks ranges.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.frames == 0 || self.frames > MAX_FRAMES {
            return Err(FieldError::new(
                "animation.frames",
                format!("must be 1 to {MAX_FRAMES}, got {}", self.frames),
            ));
        }
        check_finite("animation.fps", self.fps)?;
        if !(self.fps > 0.0 && self.fps <= 1000.0) {
            return Err(FieldError::new(
                "animation.fps",
                format!("must be > 0 and at most 1000, got {}", self.fps),
            ));
        }
        Ok(())
    }
}

/// An object's transform at one frame; between keyframes each field is interpolated
/// linearly, before the first and after the last it holds.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Keyframe {
    pub frame: u32,
    #[serde(default)]
    pub translate: [f32; 3],
    /// Degrees about X, then Y, then Z (as in `transform`); interpolated as numbers, so a
    /// turn of 360° between two keyframes is a whole turn.
    #[serde(default)]
    pub rotate_deg: [f32; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<Scale>,
}

impl Keyframe {
    /// The transform at `frame` of the sorted `keys` (at least one).
    pub fn at(keys: &[Keyframe], frame: u32) -> Transform {
        let lerp = |a: [f32; 3], b: [f32; 3], t: f32| [0, 1, 2].map(|k| a[k] + (b[k] - a[k]) * t);
        let scale = |k: &Keyframe| k.scale.map_or([1.0; 3], Scale::as_vec);
        let of = |k: &Keyframe| Transform {
            translate: k.translate,
            rotate_deg: k.rotate_deg,
            scale: k.scale,
        };
        let Some(next) = keys.iter().position(|k| k.frame >= frame) else {
            return keys.last().map(of).unwrap_or_default();
        };
        if next == 0 || keys[next].frame == frame {
            return of(&keys[next]);
        }
        let (a, b) = (&keys[next - 1], &keys[next]);
        let t = (frame - a.frame) as f32 / (b.frame - a.frame) as f32;
        let s = lerp(scale(a), scale(b), t);
        Transform {
            translate: lerp(a.translate, b.translate, t),
            rotate_deg: lerp(a.rotate_deg, b.rotate_deg, t),
            scale: (a.scale.is_some() || b.scale.is_some()).then_some(Scale::PerAxis(s)),
        }
    }

    /// Checks `keys` of the object at `at` against an animation of `frames` frames.
    pub fn validate_all(keys: &[Keyframe], at: &str, frames: u32) -> Result<(), FieldError> {
        if keys.is_empty() {
            return Err(FieldError::new(
                at,
                "must list at least one keyframe (or leave `keyframes` out)",
            ));
        }
        for (i, k) in keys.iter().enumerate() {
            let here = format!("{at}[{i}]");
            if k.frame >= frames {
                return Err(FieldError::new(
                    format!("{here}.frame"),
                    format!(
                        "frame {} is out of range: the animation has {frames} frames (0 to {})",
                        k.frame,
                        frames - 1
                    ),
                ));
            }
            if i > 0 && k.frame <= keys[i - 1].frame {
                return Err(FieldError::new(
                    format!("{here}.frame"),
                    "keyframes must be listed in increasing frame order, each frame once",
                ));
            }
            check_vec_finite(&format!("{here}.translate"), &k.translate)?;
            check_vec_finite(&format!("{here}.rotate_deg"), &k.rotate_deg)?;
            if let Some(s) = k.scale {
                for (c, v) in s.as_vec().iter().enumerate() {
                    check_finite(&format!("{here}.scale"), *v)?;
                    if *v == 0.0 {
                        return Err(FieldError::new(
                            format!("{here}.scale[{c}]"),
                            "must not be 0 (a flat object has no area)",
                        ));
                    }
                }
            }
        }
        Ok(())
    }
}

/// Whether an OBJ path holds a `{frame}` pattern.
pub fn is_frame_pattern(path: &str) -> bool {
    path.contains("{frame")
}

/// `path` with each `{frame}` replaced by `number`, and each `{frame:0N}` by `number`
/// zero-padded to N digits (`horse_{frame:02}.obj`, 7 → `horse_07.obj`). An error names a
/// malformed pattern.
pub fn frame_mesh_path(path: &str, number: u32) -> Result<String, String> {
    let mut out = String::with_capacity(path.len() + 4);
    let mut rest = path;
    while let Some(at) = rest.find("{frame") {
        out.push_str(&rest[..at]);
        let tail = &rest[at + "{frame".len()..];
        let Some(close) = tail.find('}') else {
            return Err(format!(
                "\"{path}\": a `{{frame` pattern without its closing `}}`"
            ));
        };
        let spec = &tail[..close];
        if spec.is_empty() {
            out.push_str(&number.to_string());
        } else {
            let width = spec
                .strip_prefix(":0")
                .and_then(|w| w.parse::<usize>().ok())
                .filter(|w| (1..=9).contains(w))
                .ok_or_else(|| {
                    format!(
                        "\"{path}\": `{{frame{spec}}}` is not a frame pattern; write `{{frame}}` \
                         or `{{frame:0N}}` (N digits, zero-padded, N from 1 to 9)"
                    )
                })?;
            out.push_str(&format!("{number:0width$}"));
        }
        rest = &tail[close + 1..];
    }
    out.push_str(rest);
    Ok(out)
}

/// `sequence.json`: the frames of an animated scene, each a bundle folder beside it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SequenceManifest {
    /// Always [`SEQUENCE_FORMAT`].
    pub format: String,
    /// [`SEQUENCE_VERSION`].
    pub version: u32,
    /// The scene's name.
    pub name: String,
    pub fps: f32,
    /// Frame k's bundle folder, relative to this file; frames whose scene is the same as an
    /// earlier frame's (nothing moved) share its folder.
    pub frames: Vec<String>,
}

impl SequenceManifest {
    /// Checks the format, the version and that every frame names a plain sub-folder.
    pub fn validate(&self) -> Result<(), String> {
        if self.format != SEQUENCE_FORMAT {
            return Err(format!(
                "format is {:?}, not {SEQUENCE_FORMAT:?}",
                self.format
            ));
        }
        if self.version != SEQUENCE_VERSION {
            return Err(format!(
                "sequence version {} (this build reads version {SEQUENCE_VERSION})",
                self.version
            ));
        }
        if self.frames.is_empty() || self.frames.len() > MAX_FRAMES as usize {
            return Err(format!(
                "{} frames (1 to {MAX_FRAMES} are allowed)",
                self.frames.len()
            ));
        }
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(format!("fps {} is not a positive number", self.fps));
        }
        for (k, f) in self.frames.iter().enumerate() {
            let plain = !f.is_empty()
                && !f.starts_with('.')
                && f.chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
            if !plain {
                return Err(format!(
                    "frame {k}'s folder {f:?} is not a plain sub-folder name"
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_patterns_expand_and_bad_ones_are_named() {
        assert_eq!(frame_mesh_path("h_{frame}.obj", 7).unwrap(), "h_7.obj");
        assert_eq!(frame_mesh_path("h_{frame:03}.obj", 7).unwrap(), "h_007.obj");
        assert_eq!(
            frame_mesh_path("{frame:02}/h_{frame:02}.obj", 12).unwrap(),
            "12/h_12.obj"
        );
        assert_eq!(frame_mesh_path("plain.obj", 3).unwrap(), "plain.obj");
        assert!(
            frame_mesh_path("h_{frame.obj", 1)
                .unwrap_err()
                .contains("closing")
        );
        assert!(
            frame_mesh_path("h_{frame:x}.obj", 1)
                .unwrap_err()
                .contains("{frame:0N}")
        );
    }

    #[test]
    fn keyframes_interpolate_and_hold() {
        let keys = vec![
            Keyframe {
                frame: 2,
                translate: [0.0, 0.0, 0.0],
                rotate_deg: [0.0, 0.0, 0.0],
                scale: None,
            },
            Keyframe {
                frame: 6,
                translate: [4.0, 0.0, -8.0],
                rotate_deg: [0.0, 360.0, 0.0],
                scale: Some(Scale::Uniform(3.0)),
            },
        ];
        assert_eq!(Keyframe::at(&keys, 0).translate, [0.0; 3]);
        let mid = Keyframe::at(&keys, 3);
        assert_eq!(mid.translate, [1.0, 0.0, -2.0]);
        assert_eq!(mid.rotate_deg, [0.0, 90.0, 0.0]);
        assert_eq!(mid.scale, Some(Scale::PerAxis([1.5; 3])));
        assert_eq!(Keyframe::at(&keys, 9).translate, [4.0, 0.0, -8.0]);
        assert!(Keyframe::validate_all(&keys, "k", 6).is_err());
        assert!(Keyframe::validate_all(&keys, "k", 7).is_ok());
        let mut backwards = keys.clone();
        backwards.reverse();
        assert!(
            Keyframe::validate_all(&backwards, "k", 10)
                .unwrap_err()
                .to_string()
                .contains("increasing")
        );
    }
}
