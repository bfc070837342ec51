//! The light one render has and another lacks, as a picture: the paper's "missing light
//! transport component" images (Figs. 1 b, 9 b, 10 b: full transport minus subsurface
//! scattering only).
//!
//! In: two linear OpenEXR renders of the same view (`translux-server render --out X.exr`,
//! unscaled), an exposure in EV and a tone curve. Out: a PNG of max(A − B, 0) × 2^EV through
//! the tone curve and the sRGB encoding, the renderer's own display mapping
//! ([`translux_engine::render::display_rgb8`]).
//!
//! ```sh
//! cargo run --release -p translux-tests --example exrdiff -- full.exr sss.exr missing.png 1 filmic
//! ```

use anyhow::{Context, bail};
use translux_proto::api::ToneMap;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [a, b, out, ev, rest @ ..] = args.as_slice() else {
        bail!("usage: exrdiff A.exr B.exr OUT.png EV [filmic|srgb]");
    };
    let tone = match rest.first().map(String::as_str) {
        None | Some("filmic") => ToneMap::Filmic,
        Some("srgb") => ToneMap::Srgb,
        Some(other) => bail!("tone curve {other:?}: filmic or srgb"),
    };
    let ev: f32 = ev
        .parse()
        .with_context(|| format!("EV {ev:?} is not a number"))?;
    let read = |p: &str| -> anyhow::Result<image::Rgb32FImage> {
        Ok(image::open(p)
            .with_context(|| format!("cannot read {p}"))?
            .into_rgb32f())
    };
    let (a, b) = (read(a)?, read(b)?);
    if a.dimensions() != b.dimensions() {
        bail!(
            "the renders differ in size: {:?} and {:?}",
            a.dimensions(),
            b.dimensions()
        );
    }
    let scale = ev.exp2();
    let img = image::RgbImage::from_fn(a.width(), a.height(), |x, y| {
        let (p, q) = (a.get_pixel(x, y).0, b.get_pixel(x, y).0);
        let d = [0, 1, 2].map(|c| (p[c] - q[c]).max(0.0));
        image::Rgb(translux_engine::render::display_rgb8(d, scale, tone))
    });
    img.save(out)
        .with_context(|| format!("cannot write {out}"))?;
    Ok(())
}
