//! Rooms made the way users make them: one OBJ per wall (a single quad facing into the
//! room), or the whole room as one closed OBJ box facing inward, with a box standing on the
//! floor and a point light. Written as files beside a JSON scene file, in any unit and with
//! the scene's origin anywhere.
//!
//! In: a [`RoomSpec`]. Out: the scene file's path in a folder of the caller's.

use std::path::{Path, PathBuf};

use serde_json::{Value, json};

/// How the room's surfaces are modelled.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Walls {
    /// Six OBJ files of one quad each (floor, ceiling, four walls), facing inward.
    SeparateQuads,
    /// One OBJ of a closed box (shared corners), every face facing inward.
    OneClosedBox,
}

/// A cubic room of side `size` (scene units) with its minimum corner at `corner`.
#[derive(Debug, Clone)]
pub struct RoomSpec {
    pub size: f32,
    pub corner: [f32; 3],
    /// Millimetres per scene unit (1000: metres, 1: millimetres).
    pub unit_mm: f64,
    pub walls: Walls,
    /// The `orientation` written for the room's objects (`None`: not written, so `auto`).
    pub orientation: Option<&'static str>,
    /// Albedo of the walls, floor and ceiling.
    pub albedo: f32,
    /// Patch target of the scene file.
    pub patches: u64,
}

impl RoomSpec {
    /// A 1 m room at `corner`, walls as separate quads, albedo 0.6, 1500 patches.
    pub fn metres(corner: [f32; 3]) -> RoomSpec {
        RoomSpec {
            size: 1.0,
            corner,
            unit_mm: 1000.0,
            walls: Walls::SeparateQuads,
            orientation: None,
            albedo: 0.6,
            patches: 1500,
        }
    }

    /// The room's point light, 0.3 of the room's height under the ceiling's centre.
    pub fn light(&self) -> Value {
        json!({
            "type": "point",
            "position": self.at([0.5, 0.7, 0.5]),
            "intensity": [0.8, 0.8, 0.8],
        })
    }

    /// A point given in fractions of the room.
    pub fn at(&self, f: [f32; 3]) -> [f32; 3] {
        [0, 1, 2].map(|k| self.corner[k] + f[k] * self.size)
    }

    /// The room's inner box standing on the floor: its min and max corners.
    pub fn block(&self) -> ([f32; 3], [f32; 3]) {
        (self.at([0.3, 0.0, 0.35]), self.at([0.6, 0.35, 0.65]))
    }

    /// Names of the room's surface objects (walls, floor, ceiling).
    pub fn surface_names(&self) -> Vec<&'static str> {
        match self.walls {
            Walls::SeparateQuads => FACES.iter().map(|f| f.0).collect(),
            Walls::OneClosedBox => vec!["room"],
        }
    }
}

/// The six faces of the unit cube, corners counter-clockwise seen from inside the cube.
const FACES: [(&str, [[f32; 3]; 4]); 6] = [
    (
        "floor",
        [[0., 0., 0.], [0., 0., 1.], [1., 0., 1.], [1., 0., 0.]],
    ),
    (
        "ceiling",
        [[0., 1., 0.], [1., 1., 0.], [1., 1., 1.], [0., 1., 1.]],
    ),
    (
        "back",
        [[0., 0., 0.], [1., 0., 0.], [1., 1., 0.], [0., 1., 0.]],
    ),
    (
        "front",
        [[0., 0., 1.], [0., 1., 1.], [1., 1., 1.], [1., 0., 1.]],
    ),
    (
        "left",
        [[0., 0., 0.], [0., 1., 0.], [0., 1., 1.], [0., 0., 1.]],
    ),
    (
        "right",
        [[1., 0., 0.], [1., 0., 1.], [1., 1., 1.], [1., 1., 0.]],
    ),
];

/// OBJ text of an axis-aligned box from `lo` to `hi` with shared corners, faces outward
/// (`inward`: reversed).
pub fn box_obj(lo: [f32; 3], hi: [f32; 3], inward: bool) -> String {
    let mut s = String::from("# box exported as one closed mesh\n");
    for k in 0..8 {
        let p = [
            if k & 1 == 1 { hi[0] } else { lo[0] },
            if k & 2 == 2 { hi[1] } else { lo[1] },
            if k & 4 == 4 { hi[2] } else { lo[2] },
        ];
        s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    // Vertex index of the unit-cube corner (x, y, z), 1-based.
    let idx = |c: [f32; 3]| 1 + c[0] as usize + 2 * c[1] as usize + 4 * c[2] as usize;
    for (_, q) in FACES {
        // FACES wind inward; outward is the reverse.
        let mut v = q.map(idx);
        if !inward {
            v.reverse();
        }
        s += &format!(
            "f {} {} {}\nf {} {} {}\n",
            v[0], v[1], v[2], v[0], v[2], v[3]
        );
    }
    s
}

/// Writes the room's OBJ files and `room.json` into `dir`; returns the scene file's path.
pub fn write_room(dir: &Path, spec: &RoomSpec) -> PathBuf {
    let grey = json!({"type": "diffuse", "albedo": vec![spec.albedo; 3]});
    let mut objects = Vec::new();
    let mut push = |name: &str, file: String, text: String| {
        std::fs::write(dir.join(&file), text).unwrap();
        let mut o = json!({"name": name, "mesh": file, "material": grey});
        if let Some(mode) = spec.orientation {
            o["orientation"] = json!(mode);
        }
        objects.push(o);
    };
    match spec.walls {
        Walls::SeparateQuads => {
            for (name, q) in FACES {
                let mut s = format!("# {name}: one quad facing into the room\n");
                for c in q {
                    let p = spec.at(c);
                    s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
                }
                s += "f 1 2 3 4\n";
                push(name, format!("{name}.obj"), s);
            }
        }
        Walls::OneClosedBox => {
            let (lo, hi) = (spec.at([0.0; 3]), spec.at([1.0; 3]));
            push("room", "room.obj".into(), box_obj(lo, hi, true));
        }
    }
    let (lo, hi) = spec.block();
    std::fs::write(dir.join("block.obj"), box_obj(lo, hi, false)).unwrap();
    objects.push(json!({
        "name": "block", "mesh": "block.obj",
        "material": {"type": "diffuse", "albedo": [0.7, 0.5, 0.3]},
    }));
    let scene = json!({
        "unit_mm": spec.unit_mm,
        "patches": {"target": spec.patches},
        "objects": objects,
        "lights": [spec.light()],
    });
    let path = dir.join("room.json");
    std::fs::write(&path, serde_json::to_string_pretty(&scene).unwrap()).unwrap();
    path
}
