//! glTF 2.0 files as whole scenes (issue 84, item 1): fixtures written here the way
//! Blender's exporter writes them (named nodes, `extensionsUsed`, one buffer as a base64
//! data URI in `.gltf` or the BIN chunk of a `.glb`, PNG textures made with `image`), then
//! loaded, precomputed and relit through the engine.

use std::path::{Path, PathBuf};

use base64::Engine as _;
use serde_json::{Value, json};
use translux_engine::radiosity::{self, Method, Rgb, SolveParams, SparseScatter};
use translux_engine::transport::Transport;
use translux_precompute::gltf_scene::single_scattering_albedo;
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_proto::bundle::Bundle;
use translux_proto::light::Light;
use translux_proto::scene::{Material, Profile};

/// A glTF file being written: the JSON root and its one binary buffer.
struct Fixture {
    root: Value,
    bin: Vec<u8>,
}

impl Fixture {
    fn new() -> Fixture {
        Fixture {
            root: json!({
                "asset": {"generator": "Khronos glTF Blender I/O (translux test)", "version": "2.0"},
                "scene": 0,
                "scenes": [{"name": "Scene", "nodes": []}],
                "nodes": [], "meshes": [], "materials": [], "accessors": [], "bufferViews": [],
            }),
            bin: Vec::new(),
        }
    }

    fn push(&mut self, key: &str, v: Value) -> usize {
        let a = self.root[key].as_array_mut().unwrap();
        a.push(v);
        a.len() - 1
    }

    /// A buffer view of `bytes` (4-byte aligned) and an accessor over it.
    fn accessor(
        &mut self,
        bytes: &[u8],
        count: usize,
        ty: &str,
        ctype: u32,
        extra: Value,
    ) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let view = self.push(
            "bufferViews",
            json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len()}),
        );
        self.bin.extend_from_slice(bytes);
        let mut acc =
            json!({"bufferView": view, "componentType": ctype, "count": count, "type": ty});
        if let Value::Object(m) = extra {
            for (k, v) in m {
                acc[k] = v;
            }
        }
        self.push("accessors", acc)
    }

    fn material(&mut self, m: Value) -> usize {
        self.push("materials", m)
    }

    /// A mesh of quads (each `[centre, u, v]`, facing u × v, corners c ± u ± v with UVs
    /// 0..1 along u and v) with one material, placed by a root node named `name` at
    /// `translation`.
    fn quads(
        &mut self,
        name: &str,
        quads: &[[[f32; 3]; 3]],
        material: usize,
        translation: [f32; 3],
    ) -> usize {
        let (mut pos, mut uv, mut idx) = (Vec::<f32>::new(), Vec::<f32>::new(), Vec::<u16>::new());
        for q in quads {
            let [c, u, v] = q;
            let base = (pos.len() / 3) as u16;
            for (su, sv) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                for k in 0..3 {
                    pos.push(c[k] + su * u[k] + sv * v[k]);
                }
                uv.extend([(su + 1.0) / 2.0, (sv + 1.0) / 2.0]);
            }
            idx.extend([base, base + 1, base + 2, base, base + 2, base + 3]);
        }
        let n = pos.len() / 3;
        let (lo, hi) = (0..3).fold(([f32::MAX; 3], [f32::MIN; 3]), |(mut lo, mut hi), k| {
            for p in pos.chunks(3) {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
            (lo, hi)
        });
        let p = self.accessor(
            bytemuck::cast_slice(&pos),
            n,
            "VEC3",
            5126,
            json!({"min": lo, "max": hi}),
        );
        let t = self.accessor(bytemuck::cast_slice(&uv), n, "VEC2", 5126, json!({}));
        let i = self.accessor(
            bytemuck::cast_slice(&idx),
            idx.len(),
            "SCALAR",
            5123,
            json!({}),
        );
        let mesh = self.push(
            "meshes",
            json!({"name": format!("{name}Mesh"), "primitives": [{
                "attributes": {"POSITION": p, "TEXCOORD_0": t}, "indices": i, "material": material}]}),
        );
        self.node(json!({"name": name, "mesh": mesh, "translation": translation}))
    }

    /// A root node.
    fn node(&mut self, n: Value) -> usize {
        let k = self.push("nodes", n);
        self.root["scenes"][0]["nodes"]
            .as_array_mut()
            .unwrap()
            .push(json!(k));
        k
    }

    /// A PNG image (sRGB, as glTF says) in the buffer, and a texture of it with `sampler`.
    fn texture(&mut self, img: &image::RgbImage, sampler: Value) -> usize {
        let mut png = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let view = self.push(
            "bufferViews",
            json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": png.len()}),
        );
        self.bin.extend_from_slice(&png);
        if self.root.get("images").is_none() {
            self.root["images"] = json!([]);
            self.root["textures"] = json!([]);
            self.root["samplers"] = json!([]);
        }
        let image = self.push(
            "images",
            json!({"name": "tex", "mimeType": "image/png", "bufferView": view}),
        );
        let s = self.push("samplers", sampler);
        self.push("textures", json!({"sampler": s, "source": image}))
    }

    /// A KHR_lights_punctual light placed by a node (child of a parent node at `parent`).
    fn light(&mut self, light: Value, parent: [f32; 3], at: [f32; 3]) {
        let exts = &mut self.root["extensions"];
        if exts.is_null() {
            *exts = json!({"KHR_lights_punctual": {"lights": []}});
        }
        let lights = self.root["extensions"]["KHR_lights_punctual"]["lights"]
            .as_array_mut()
            .unwrap();
        lights.push(light);
        let l = lights.len() - 1;
        let child = self.push(
            "nodes",
            json!({"name": "LampNode", "translation": at,
                   "extensions": {"KHR_lights_punctual": {"light": l}}}),
        );
        self.node(json!({"name": "LampParent", "translation": parent, "children": [child]}));
    }

    fn uses(&mut self, ext: &str, required: bool) {
        for key in ["extensionsUsed"]
            .into_iter()
            .chain(required.then_some("extensionsRequired"))
        {
            let list = self.root[key]
                .as_array_mut()
                .map(std::mem::take)
                .unwrap_or_default();
            let mut list = list;
            list.push(json!(ext));
            self.root[key] = Value::Array(list);
        }
    }

    /// Writes `.gltf` (the buffer as a base64 data URI) or `.glb` (a BIN chunk), by the
    /// name's extension.
    fn write(mut self, path: &Path) -> PathBuf {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let glb = path.extension().is_some_and(|e| e == "glb");
        self.root["buffers"] = if glb {
            json!([{"byteLength": self.bin.len()}])
        } else {
            let data = base64::engine::general_purpose::STANDARD.encode(&self.bin);
            json!([{"byteLength": self.bin.len(),
                    "uri": format!("data:application/octet-stream;base64,{data}")}])
        };
        let mut text = serde_json::to_vec(&self.root).unwrap();
        if glb {
            while !text.len().is_multiple_of(4) {
                text.push(b' ');
            }
            let total = 12 + 8 + text.len() + 8 + self.bin.len();
            let mut out = Vec::with_capacity(total);
            out.extend(b"glTF");
            out.extend(2u32.to_le_bytes());
            out.extend((total as u32).to_le_bytes());
            out.extend((text.len() as u32).to_le_bytes());
            out.extend(b"JSON");
            out.extend(&text);
            out.extend((self.bin.len() as u32).to_le_bytes());
            out.extend(b"BIN\0");
            out.extend(&self.bin);
            std::fs::write(path, out).unwrap();
        } else {
            std::fs::write(path, text).unwrap();
        }
        path.to_path_buf()
    }
}

/// A diffuse glTF material of base colour `rgb`.
fn pbr(name: &str, rgb: [f32; 3]) -> Value {
    json!({"name": name, "pbrMetallicRoughness": {
        "baseColorFactor": [rgb[0], rgb[1], rgb[2], 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.5}})
}

/// A 2 m floor facing +Y and a 2 m wall at x = −1 facing +X (base colour `wall`), 1 m high.
fn room(f: &mut Fixture, wall: [f32; 3]) {
    let white = f.material(pbr("White", [0.8, 0.8, 0.8]));
    let red = f.material(pbr("WallPaint", wall));
    f.quads(
        "Floor",
        &[[[0.0; 3], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]],
        white,
        [0.0; 3],
    );
    f.quads(
        "Wall",
        &[[[0.0, 0.5, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 1.0]]],
        red,
        [-1.0, 0.0, 0.0],
    );
}

/// Precomputes `scene` into `dir/name` at about `patches` patches.
fn build(scene: &str, dir: &Path, name: &str, patches: u64) -> Bundle {
    let loaded = load_scene(scene).unwrap_or_else(|e| panic!("{e}"));
    let out = dir.join(name);
    let params = PrecomputeParams {
        patches: Some(patches),
        progress: false,
        ..Default::default()
    };
    precompute(&loaded, &out, &params).unwrap();
    Bundle::open(&out).unwrap()
}

/// The radiosity of every patch under the bundle's own lights.
fn relight(b: &Bundle) -> Vec<Rgb> {
    let e = radiosity::BundleLighting::new(b)
        .irradiance(&b.manifest().lights)
        .unwrap();
    let params = SolveParams {
        method: Method::Jacobi,
        tolerance: 1e-6,
        max_iterations: 5000,
    };
    let (b_out, stats) = radiosity::solve(
        &Transport::of(b),
        &SparseScatter(b.subsurface()),
        b.patch_emission(),
        &e,
        &params,
        None,
    )
    .unwrap();
    assert!(stats.converged, "{stats:?}");
    b_out
}

/// The patch range of object `name`.
fn range(b: &Bundle, name: &str) -> std::ops::Range<usize> {
    let o = b
        .manifest()
        .objects
        .iter()
        .find(|o| o.name == name)
        .unwrap_or_else(|| panic!("no object {name}"));
    o.first_patch as usize..(o.first_patch + o.patch_count) as usize
}

fn centroid(b: &Bundle, p: usize) -> [f32; 3] {
    let c = b.patch_corners()[p];
    std::array::from_fn(|k| (c[0][k] + c[1][k] + c[2][k]) / 3.0)
}

#[test]
fn a_red_wall_reflects_red_onto_a_white_floor_with_no_json() {
    let dir = tempfile::tempdir().unwrap();
    let mut f = Fixture::new();
    room(&mut f, [0.8, 0.05, 0.05]);
    f.light(
        json!({"name": "Lamp", "type": "point", "color": [1, 1, 1], "intensity": 2000}),
        [0.0, 1.0, 0.0],
        [0.0, 0.5, 0.0],
    );
    f.uses("KHR_lights_punctual", false);
    // A camera 3 m out along +Z looking back (glTF cameras look along their −Z).
    f.root["cameras"] =
        json!([{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.1}}]);
    f.node(json!({"name": "Camera", "camera": 0, "translation": [0.0, 0.5, 3.0]}));
    let glb = f.write(&dir.path().join("room.glb"));
    // The command line takes the .glb itself as the scene.
    let out = dir.path().join("bundle");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_translux-precompute"))
        .arg(&glb)
        .arg("--out")
        .arg(&out)
        .args(["--patches", "400", "--quiet"])
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let b = Bundle::open(&out).unwrap();
    // Objects are the nodes, by name; the lamp is the KHR light at its world position.
    let names: Vec<&str> = b
        .manifest()
        .objects
        .iter()
        .map(|o| o.name.as_str())
        .collect();
    assert_eq!(names, ["Floor", "Wall"]);
    let [
        Light::Point {
            position,
            intensity,
        },
    ] = b.manifest().lights[..]
    else {
        panic!("{:?}", b.manifest().lights)
    };
    assert_eq!(position, [0.0, 1.5, 0.0]);
    assert!(
        (intensity[0] - 2000.0 / 683.0).abs() < 1e-5,
        "{intensity:?}"
    );
    // The file's camera is the bundle's: where the viewer starts.
    let cam = b.manifest().camera;
    assert_eq!(
        (cam.position, cam.target),
        ([0.0, 0.5, 3.0], [0.0, 0.5, 2.0])
    );
    assert!((cam.fov_deg - 0.8f32.to_degrees()).abs() < 1e-4);
    let rad = relight(&b);
    // Floor patches near the wall against those at the far side: red over green.
    let (mut near, mut far) = ([0.0f64; 3], [0.0f64; 3]);
    for p in range(&b, "Floor") {
        let x = centroid(&b, p)[0];
        let bin = if x < -0.7 {
            &mut near
        } else if x > 0.7 {
            &mut far
        } else {
            continue;
        };
        for c in 0..3 {
            bin[c] += f64::from(rad[p][c]);
        }
    }
    let (rn, rf) = (near[0] / near[1], far[0] / far[1]);
    eprintln!("floor red/green: near the wall {rn:.3}, far side {rf:.3}");
    assert!(
        rn > 1.1,
        "the floor near the red wall is not red: red/green {rn}"
    );
    assert!(rn > rf + 0.05, "near {rn} vs far {rf}");
    assert!(
        (near[1] / near[2] - 1.0).abs() < 0.02,
        "green and blue differ near the wall"
    );

    // Exporting keeps the node names: the engine's .glb has one node per object.
    let parts: Vec<translux_engine::export::MeshPart> = b
        .manifest()
        .objects
        .iter()
        .map(|o| translux_engine::export::MeshPart {
            name: o.name.clone(),
            triangles: o.first_patch as usize..(o.first_patch + o.patch_count) as usize,
        })
        .collect();
    let radiance = vec![[0.1f32; 3]; b.vertex_positions().len()];
    let mut mesh = translux_engine::export::ExportMesh::new(
        b.vertex_positions(),
        b.vertex_normals(),
        b.triangle_vertices(),
        &radiance,
    );
    mesh.parts = &parts;
    mesh.unit_mm = b.manifest().unit_mm;
    let bytes =
        translux_engine::export::to_glb(&mesh, 0.0, translux_proto::api::ToneMap::Srgb).unwrap();
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    let exported: Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
    let nodes: Vec<&str> = exported["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n["name"].as_str().unwrap())
        .collect();
    assert_eq!(nodes, ["Floor", "Wall"]);
}

#[test]
fn a_textured_floor_follows_the_texture_mean_over_each_patch() {
    let dir = tempfile::tempdir().unwrap();
    let mut f = Fixture::new();
    // Left half (u < 0.5) black, right half sRGB 200 (linear 0.578).
    let img = image::RgbImage::from_fn(64, 64, |x, _| {
        if x < 32 {
            image::Rgb([0, 0, 0])
        } else {
            image::Rgb([200, 200, 200])
        }
    });
    let tex = f.texture(
        &img,
        json!({"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}),
    );
    let m = f.material(json!({"name": "Checker", "pbrMetallicRoughness": {
        "baseColorFactor": [1.0, 1.0, 1.0, 1.0], "baseColorTexture": {"index": tex}}}));
    // u runs along +Z: the floor's z < 0 is black.
    f.quads(
        "Floor",
        &[[[0.0; 3], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]],
        m,
        [0.0; 3],
    );
    f.light(
        json!({"type": "point", "intensity": 1000}),
        [0.0; 3],
        [0.0, 1.0, 0.0],
    );
    f.uses("KHR_lights_punctual", false);
    f.write(&dir.path().join("floor.gltf"));
    let b = build(
        dir.path().join("floor.gltf").to_str().unwrap(),
        dir.path(),
        "floor",
        300,
    );
    let white = translux_precompute::gltf_scene::srgb_to_linear(200.0 / 255.0);
    let albedo = b.patch_albedo();
    let s = b.subsurface();
    let (mut dark, mut light) = (0, 0);
    for p in range(&b, "Floor") {
        let z = centroid(&b, p)[2];
        let want = if z < -0.1 {
            dark += 1;
            0.0
        } else if z > 0.1 {
            light += 1;
            white
        } else {
            continue;
        };
        for c in 0..3 {
            assert!(
                (albedo[p][c] - want).abs() < 0.01,
                "patch {p} at z = {z}: albedo {:?}, want {want}",
                albedo[p]
            );
        }
        // S_pp is the same ρ: the transport sees the texture too.
        let (cols, vals) = s.row(p);
        let k = cols.iter().position(|&c| c as usize == p).unwrap();
        assert_eq!(vals[k], albedo[p], "S_pp of patch {p}");
    }
    assert!(
        dark > 50 && light > 50,
        "{dark} dark and {light} light patches"
    );
    // The object's albedo is the area mean: half of the light half's.
    let Material::Diffuse { albedo: mean, .. } = &b.manifest().objects[0].material else {
        panic!("{:?}", b.manifest().objects[0].material)
    };
    assert!(
        (mean[0] - white / 2.0).abs() < 0.01,
        "object albedo {mean:?}"
    );
}

#[test]
fn a_khr_point_light_answers_as_the_equivalent_json_light() {
    let dir = tempfile::tempdir().unwrap();
    let mut f = Fixture::new();
    room(&mut f, [0.6, 0.3, 0.1]);
    // 1366 cd of a warm colour, 1.5 m up through a parent node.
    f.light(
        json!({"name": "Lamp", "type": "point", "color": [1.0, 0.8, 0.6], "intensity": 1366}),
        [0.2, 1.0, 0.1],
        [0.0, 0.5, 0.0],
    );
    f.uses("KHR_lights_punctual", false);
    f.write(&dir.path().join("room.glb"));
    // The same room with its lights replaced by the JSON light the docs give: W·sr⁻¹ = cd / 683.
    let json_scene = dir.path().join("room.json");
    std::fs::write(
        &json_scene,
        r#"{"gltf": "room.glb", "lights": [{"type": "point", "position": [0.2, 1.5, 0.1],
            "intensity": [2.0, 1.6, 1.2]}]}"#,
    )
    .unwrap();
    let a = build(
        dir.path().join("room.glb").to_str().unwrap(),
        dir.path(),
        "khr",
        300,
    );
    let b = build(json_scene.to_str().unwrap(), dir.path(), "json", 300);
    let (ra, rb) = (relight(&a), relight(&b));
    assert_eq!(ra.len(), rb.len());
    let peak = rb.iter().flatten().fold(0.0f32, |m, &v| m.max(v));
    assert!(peak > 0.0);
    for (p, (x, y)) in ra.iter().zip(&rb).enumerate() {
        for c in 0..3 {
            assert!(
                (x[c] - y[c]).abs() <= 1e-4 * peak,
                "patch {p} channel {c}: KHR {} vs JSON {}",
                x[c],
                y[c]
            );
        }
    }
}

/// What docs/scenes.md says a glTF volume becomes (mm⁻¹), computed here independently.
fn documented_medium(
    att: [f32; 3],
    dist_m: f32,
    scatter: [f32; 3],
    g: f32,
) -> ([f32; 3], [f32; 3]) {
    let mut sa = [0.0; 3];
    let mut ss = [0.0; 3];
    for c in 0..3 {
        let st = -att[c].ln() / (dist_m * 1000.0);
        let a = scatter[c];
        let s = 4.09712 + 4.20863 * a - (9.59217 + 41.6808 * a + 17.7126 * a * a).sqrt();
        let alpha = 1.0 - s * s;
        sa[c] = (1.0 - alpha) * st;
        ss[c] = alpha * st * (1.0 - g);
    }
    (sa, ss)
}

/// A closed box of half-size `h` at `at` (six quads facing out).
fn cube(f: &mut Fixture, name: &str, h: f32, at: [f32; 3], material: usize) {
    let q = |c: [f32; 3], u: [f32; 3], v: [f32; 3]| [c, u, v];
    f.quads(
        name,
        &[
            q([h, 0.0, 0.0], [0.0, h, 0.0], [0.0, 0.0, h]),
            q([-h, 0.0, 0.0], [0.0, 0.0, h], [0.0, h, 0.0]),
            q([0.0, h, 0.0], [0.0, 0.0, h], [h, 0.0, 0.0]),
            q([0.0, -h, 0.0], [h, 0.0, 0.0], [0.0, 0.0, h]),
            q([0.0, 0.0, h], [h, 0.0, 0.0], [0.0, h, 0.0]),
            q([0.0, 0.0, -h], [0.0, h, 0.0], [h, 0.0, 0.0]),
        ],
        material,
        at,
    );
}

#[test]
fn a_volume_material_becomes_the_documented_medium() {
    let dir = tempfile::tempdir().unwrap();
    let mut f = Fixture::new();
    let (att, dist, scatter, g) = ([0.8, 0.5, 0.2], 0.01, [0.9, 0.7, 0.5], 0.3);
    let wax = f.material(json!({"name": "Wax",
        "pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.8, 0.7, 1.0]},
        "extensions": {
            "KHR_materials_transmission": {"transmissionFactor": 1.0},
            "KHR_materials_volume": {"thicknessFactor": 0.05, "attenuationDistance": dist,
                                     "attenuationColor": att},
            "KHR_materials_volume_scatter": {"multiscatterColor": scatter, "scatterAnisotropy": g},
            "KHR_materials_ior": {"ior": 1.4}}}));
    // Without volume_scatter the base colour is the multiple-scattering albedo.
    let jade = f.material(json!({"name": "Jade",
        "pbrMetallicRoughness": {"baseColorFactor": [0.3, 0.7, 0.4, 1.0]},
        "extensions": {
            "KHR_materials_diffuse_transmission": {"diffuseTransmissionFactor": 1.0},
            "KHR_materials_volume": {"thicknessFactor": 0.02, "attenuationDistance": 0.02,
                                     "attenuationColor": [0.5, 0.9, 0.6]}}}));
    cube(&mut f, "WaxCube", 0.05, [0.0, 0.05, 0.0], wax);
    cube(&mut f, "JadeCube", 0.05, [0.3, 0.05, 0.0], jade);
    f.light(
        json!({"type": "directional", "intensity": 683}),
        [0.0; 3],
        [0.0, 2.0, 0.0],
    );
    for e in [
        "KHR_lights_punctual",
        "KHR_materials_transmission",
        "KHR_materials_diffuse_transmission",
        "KHR_materials_ior",
        "KHR_materials_volume_scatter",
    ] {
        f.uses(e, false);
    }
    // Required and read by translux: loads (gltf's own list would refuse it).
    f.uses("KHR_materials_volume", true);
    f.write(&dir.path().join("cubes.glb"));
    let b = build(
        dir.path().join("cubes.glb").to_str().unwrap(),
        dir.path(),
        "cubes",
        300,
    );
    let check = |name: &str, (sa_want, ss_want): ([f32; 3], [f32; 3]), eta_want: f32| {
        let o = b
            .manifest()
            .objects
            .iter()
            .find(|o| o.name == name)
            .unwrap();
        let Material::Translucent {
            profile:
                Profile::Dipole {
                    sigma_a: Some(sa),
                    sigma_s_prime: Some(ss),
                    eta: Some(eta),
                    preset: None,
                    ..
                },
            ..
        } = &o.material
        else {
            panic!("{name}: {:?}", o.material)
        };
        for c in 0..3 {
            let close = |x: f32, y: f32| (x - y).abs() <= 1e-4 * y.abs().max(1e-3);
            assert!(
                close(sa[c], sa_want[c]),
                "{name} sigma_a {sa:?} vs {sa_want:?}"
            );
            assert!(
                close(ss[c], ss_want[c]),
                "{name} sigma_s' {ss:?} vs {ss_want:?}"
            );
        }
        assert_eq!(*eta, eta_want, "{name} eta");
    };
    check("WaxCube", documented_medium(att, dist, scatter, g), 1.4);
    check(
        "JadeCube",
        documented_medium([0.5, 0.9, 0.6], 0.02, [0.3, 0.7, 0.4], 0.0),
        1.5,
    );
    // The directional light: 683 lx is 1 W·m⁻² straight down (the node's −Z turned by no
    // rotation points along −Z; the light's direction is where it travels).
    let l = &b.manifest().lights;
    assert_eq!(
        format!("{l:?}"),
        format!(
            "{:?}",
            [Light::Directional {
                direction: [0.0, 0.0, -1.0],
                irradiance: [1.0, 1.0, 1.0]
            }]
        )
    );
    assert!((single_scattering_albedo(0.5) - 0.9).abs() < 0.05);
}

#[test]
fn an_unsupported_required_extension_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let build_file = |name: &str, required: bool| {
        let mut f = Fixture::new();
        room(&mut f, [0.5; 3]);
        f.uses("KHR_draco_mesh_compression", required);
        f.write(&dir.path().join(name))
    };
    let path = build_file("draco.gltf", true);
    let e = load_scene(path.to_str().unwrap()).unwrap_err().to_string();
    assert!(
        e.contains("\"KHR_draco_mesh_compression\"") && e.contains("extensionsRequired"),
        "{e}"
    );
    // The same file with the extension optional loads, with a note that says it is ignored.
    let path = build_file("optional.gltf", false);
    let s = load_scene(path.to_str().unwrap()).unwrap();
    let notes = s.objects[0].notes.join("\n");
    assert!(notes.contains("KHR_draco_mesh_compression"), "{notes}");
    // A scene JSON overriding a name the file does not have names the choices.
    std::fs::write(
        dir.path().join("bad.json"),
        r#"{"gltf": "optional.gltf", "materials": {"Ceiling": {"type": "diffuse", "albedo": [1, 1, 1]}}}"#,
    )
    .unwrap();
    let e = load_scene(dir.path().join("bad.json").to_str().unwrap())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("materials.Ceiling") && e.contains("Floor, Wall"),
        "{e}"
    );
}
