//! The offline commands: `translux-server render | export | relight`, no HTTP.
//!
//! In: a bundle folder, an optional JSON request file (`-` reads standard input; absent
//! means `{}`: the bundle's lights, full transport) and flags. Out: one file, written whole
//! to a temporary name beside it and renamed into place.
//!
//! | command | request file | `--out` |
//! | --- | --- | --- |
//! | `render` | a render request (`POST /render`'s body: relight fields plus `camera`, `width`, `height`, `exposure`, `tone`, `background`, `cull_backfaces`); flags override its fields | `.png` (8-bit sRGB) or `.exr` (linear radiance, half-float RGB: no tone curve or OETF; `auto` exposure leaves it unscaled) |
//! | `export` | a relight request (`POST /relight`'s body); `--exposure`, `--tone` | `.glb` (linear float colours, metres, one node per object) or `.ply` (8-bit sRGB colours, scene units) |
//!
//! Exposure: `render` auto-exposes unless the request or `--exposure` gives a number, with
//! the viewer's rule ([`picture::resolve_exposure`]); so does `export` unless `--exposure`
//! gives a number. The log line of each says which EV was used and whether it was automatic.
//! | `relight` | a relight request | `.f32` (n × 3 little-endian `f32`, the binary API answer) or `.json` (the JSON API answer) |
//!
//! The work is the server's own ([`translux_engine::relight`], [`translux_engine::picture`]), so an offline answer
//! equals the HTTP answer for the same request; errors carry the same messages.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Subcommand;
use serde::de::DeserializeOwned;
use translux_proto::api::{Exposure, RelightRequest, RelightResponse, RenderRequest, ToneMap};

use crate::state::Scene;
use translux_engine::picture::{self, MeshFormat, PictureFormat};
use translux_engine::relight;

/// The offline commands: one bundle, one request, one file out, no HTTP.
#[derive(Debug, Clone, Subcommand)]
pub enum Command {
    /// Relight a bundle and render it from a camera to a PNG.
    Render(RenderArgs),
    /// Relight a bundle and write its mesh with baked vertex colours (.glb or .ply).
    Export(ExportArgs),
    /// Relight a bundle and write the per-vertex radiance B/pi (.f32 or .json).
    Relight(RelightArgs),
    /// Make or hash access tokens for the tokens file (--tokens).
    #[command(subcommand)]
    Token(crate::auth::TokenCommand),
}

/// `translux-server render`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    after_help = "The request is POST /api/v1/scenes/{id}/render's body: the relight \
    fields (lights, materials, components, solver) plus camera, width, height, exposure, tone, \
    background, cull_backfaces. Flags override the file's fields."
)]
pub struct RenderArgs {
    /// The bundle folder (written by translux-precompute).
    #[arg(long, value_name = "DIR")]
    pub bundle: PathBuf,
    /// JSON render request (`-`: standard input); default `{}`: the bundle's lights and camera.
    #[arg(long, value_name = "REQ.json")]
    pub request: Option<PathBuf>,
    /// The picture to write, by extension (any case): `.png` (8-bit sRGB, exposed and tone
    /// mapped) or `.exr` (linear radiance B/π in W·m⁻²·sr⁻¹, half-float RGB, no tone
    /// curve; a numeric exposure scales it by 2^EV, `auto` leaves it unscaled).
    #[arg(long, value_name = "FILE.png|FILE.exr")]
    pub out: PathBuf,
    /// Image width in pixels (1..=8192; default 800).
    #[arg(long)]
    pub width: Option<u32>,
    /// Image height in pixels (1..=8192; default 600).
    #[arg(long)]
    pub height: Option<u32>,
    /// Exposure: EV stops (radiance × 2^EV) or `auto` (the viewer's automatic exposure);
    /// default: the request's `exposure`, else auto.
    #[arg(long, value_name = "auto|EV", allow_negative_numbers = true)]
    pub exposure: Option<Exposure>,
    /// Tone curve: srgb (clamp) or filmic (ACES fit); default srgb.
    #[arg(long, value_name = "srgb|filmic")]
    pub tone: Option<ToneMap>,
}

/// `translux-server export`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    after_help = "glTF colours (COLOR_0) are linear floats (exposure and tone curve \
    applied, no sRGB encoding: glTF vertex colours are linear); PLY colours are 8-bit sRGB."
)]
pub struct ExportArgs {
    /// The bundle folder (written by translux-precompute).
    #[arg(long, value_name = "DIR")]
    pub bundle: PathBuf,
    /// JSON relight request (`-`: standard input); default `{}`: the bundle's lights.
    #[arg(long, value_name = "REQ.json")]
    pub request: Option<PathBuf>,
    /// The file to write: FILE.glb (binary glTF 2.0) or FILE.ply (binary PLY).
    #[arg(long, value_name = "FILE.glb|FILE.ply")]
    pub out: PathBuf,
    /// Exposure of the baked colours: EV stops or `auto` (the viewer's automatic exposure
    /// for this relight); default auto.
    #[arg(long, value_name = "auto|EV", allow_negative_numbers = true)]
    pub exposure: Option<Exposure>,
    /// Tone curve for the baked colours: srgb (clamp) or filmic (ACES fit); default srgb.
    #[arg(long, value_name = "srgb|filmic")]
    pub tone: Option<ToneMap>,
}

/// `translux-server relight`.
#[derive(Debug, Clone, clap::Args)]
pub struct RelightArgs {
    /// The bundle folder (written by translux-precompute).
    #[arg(long, value_name = "DIR")]
    pub bundle: PathBuf,
    /// JSON relight request (`-`: standard input); default `{}`: the bundle's lights.
    #[arg(long, value_name = "REQ.json")]
    pub request: Option<PathBuf>,
    /// The file to write: FILE.f32 (n × 3 little-endian f32, as the binary API) or FILE.json
    /// (as the JSON API).
    #[arg(long, value_name = "FILE.f32|FILE.json")]
    pub out: PathBuf,
}

/// Runs one offline command; the summary goes to the log (stderr).
pub fn run(command: &Command) -> anyhow::Result<()> {
    match command {
        Command::Render(a) => render(a),
        Command::Export(a) => export(a),
        Command::Relight(a) => relight_command(a),
        Command::Token(t) => crate::auth::token_command(t, &mut std::io::stdout()),
    }
}

/// The lower-case extension of `out`, or an error listing the allowed ones.
fn extension(out: &Path, allowed: &[&str]) -> anyhow::Result<String> {
    let ext = out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    if !allowed.contains(&ext.as_str()) {
        bail!(
            "--out {}: the file name must end in {}",
            out.display(),
            allowed
                .iter()
                .map(|e| format!(".{e}"))
                .collect::<Vec<_>>()
                .join(" or ")
        );
    }
    Ok(ext)
}

/// Reads the request file (`-`: standard input); `None` reads as `{}`.
fn read_request<T: DeserializeOwned>(path: Option<&Path>) -> anyhow::Result<T> {
    let (name, text) = match path {
        None => ("(none)".to_string(), "{}".to_string()),
        Some(p) if p == Path::new("-") => {
            let mut s = String::new();
            std::io::Read::read_to_string(&mut std::io::stdin(), &mut s)
                .context("cannot read the request from standard input")?;
            ("standard input".to_string(), s)
        }
        Some(p) => (
            p.display().to_string(),
            std::fs::read_to_string(p)
                .with_context(|| format!("cannot read the request {}", p.display()))?,
        ),
    };
    let text = if text.trim().is_empty() { "{}" } else { &text };
    translux_proto::parse_json(text).with_context(|| format!("invalid request in {name}"))
}

/// Opens the bundle (or sequence folder) and builds its relight state; the id is the
/// folder's name; `frame` picks an animated scene's frame (the request's `frame`).
fn open_scene(dir: &Path, frame: Option<u32>) -> anyhow::Result<std::sync::Arc<Scene>> {
    let id = dir
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("bundle")
        .to_string();
    let t = Instant::now();
    let scene = Scene::open(id, dir)
        .with_context(|| format!("cannot open the bundle {}", dir.display()))?;
    tracing::info!(
        "opened {} ({} patches, {} vertices) in {:.0} ms",
        dir.display(),
        scene.bundle.manifest().patch_count,
        scene.bundle.manifest().vertex_count,
        t.elapsed().as_secs_f64() * 1e3
    );
    std::sync::Arc::new(scene)
        .frame(frame)
        .map_err(|e| anyhow::anyhow!("{}", e.message))
}

/// Writes `bytes` to `out` through a temporary file beside it, so that a reader never sees
/// half a file.
fn write_file(out: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp: PathBuf = out.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    std::fs::write(&tmp, bytes).with_context(|| format!("cannot write {}", tmp.display()))?;
    if let Err(e) = std::fs::rename(&tmp, out) {
        let _ = std::fs::remove_file(&tmp);
        bail!("cannot move {} to {}: {e}", tmp.display(), out.display());
    }
    Ok(())
}

fn render(a: &RenderArgs) -> anyhow::Result<()> {
    let format = match extension(&a.out, &["png", "exr"])?.as_str() {
        "exr" => PictureFormat::Exr,
        _ => PictureFormat::Png,
    };
    let mut req: RenderRequest = read_request(a.request.as_deref())?;
    if let Some(w) = a.width {
        req.width = w;
    }
    if let Some(h) = a.height {
        req.height = h;
    }
    if let Some(e) = a.exposure {
        req.exposure = e;
    }
    if let Some(t) = a.tone {
        req.tone = t;
    }
    let scene = open_scene(&a.bundle, req.frame)?;
    let plan = picture::plan(&scene, req).map_err(|e| anyhow::anyhow!("{}", e.message))?;
    let plan = picture::RenderPlan { format, ..plan };
    let out = picture::run(&scene, &plan).map_err(|e| anyhow::anyhow!("{}", e.message))?;
    write_file(&a.out, &out.bytes)?;
    tracing::info!(
        "wrote {} ({}×{}, {} bytes, exposure {}): relight {:.0} ms ({} iterations), \
         raster {:.0} ms, {} {:.0} ms",
        a.out.display(),
        plan.params.width,
        plan.params.height,
        out.bytes.len(),
        match (format, plan.exposure) {
            (PictureFormat::Exr, Exposure::Auto) => "none (auto: EXR radiance unscaled)".into(),
            _ => exposure_note(plan.exposure, out.exposure),
        },
        out.stats.ms,
        out.stats.iterations,
        out.raster_ms,
        format.name(),
        out.encode_ms
    );
    Ok(())
}

fn export(a: &ExportArgs) -> anyhow::Result<()> {
    let format = match extension(&a.out, &["glb", "ply"])?.as_str() {
        "glb" => MeshFormat::Glb,
        _ => MeshFormat::Ply,
    };
    let req: RelightRequest = read_request(a.request.as_deref())?;
    let scene = open_scene(&a.bundle, req.frame)?;
    let plan = relight::plan(&scene, req).map_err(|e| anyhow::anyhow!("{}", e.message))?;
    let tone = a.tone.unwrap_or(ToneMap::Srgb);
    let exposure = a.exposure.unwrap_or_default();
    let out = picture::export(&scene, &plan, exposure, tone, format)
        .map_err(|e| anyhow::anyhow!("{}", e.message))?;
    write_file(&a.out, &out.bytes)?;
    tracing::info!(
        "wrote {} ({} bytes, {} triangles, {} objects, exposure {}): relight {:.0} ms \
         ({} iterations)",
        a.out.display(),
        out.bytes.len(),
        scene.bundle.triangle_vertices().len(),
        scene.bundle.manifest().objects.len(),
        exposure_note(exposure, out.exposure),
        out.stats.ms,
        out.stats.iterations
    );
    Ok(())
}

/// "-2.4 EV (auto)" or "-1 EV": the exposure used, and whether the viewer's rule chose it.
fn exposure_note(asked: Exposure, used: f32) -> String {
    match asked {
        Exposure::Auto => format!("{used} EV (auto)"),
        Exposure::Ev(_) => format!("{used} EV"),
    }
}

fn relight_command(a: &RelightArgs) -> anyhow::Result<()> {
    let ext = extension(&a.out, &["f32", "json"])?;
    let req: RelightRequest = read_request(a.request.as_deref())?;
    let scene = open_scene(&a.bundle, req.frame)?;
    let plan = relight::plan(&scene, req).map_err(|e| anyhow::anyhow!("{}", e.message))?;
    let out = relight::run(&scene, &plan).map_err(|e| anyhow::anyhow!("{}", e.message))?;
    let vertex_count = out.radiance.len();
    let bytes = if ext == "json" {
        serde_json::to_vec(&RelightResponse {
            vertex_count,
            radiance: out.radiance.iter().flatten().copied().collect(),
            stats: out.stats.clone(),
        })
        .context("cannot serialise the answer")?
    } else {
        out.radiance
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect()
    };
    write_file(&a.out, &bytes)?;
    tracing::info!(
        "wrote {} ({vertex_count} vertices): relight {:.0} ms ({} iterations)",
        a.out.display(),
        out.stats.ms,
        out.stats.iterations
    );
    Ok(())
}
