//! How far clustering the receivers too would thin a hierarchical S's links: the
//! measurement behind the next step of issue #20 (docs/hierarchy.md, *Receiver-side
//! clustering*).
//!
//! A hierarchical S links each receiver patch j to whole source nodes k (A_k R(r_jk) on node
//! k's area-weighted mean), so a translucency change reads one link per (patch, node) pair:
//! 71–77% of the entries at the paper's sizes. Classical hierarchical radiosity links node
//! to node instead and pushes a node's gathered value down to its patches. This counts, on a
//! bundle as it is, how many node-to-node links would carry the same links: for every
//! source node k, the receivers linking it are covered by the fewest tree nodes m that hold
//! only such receivers and are small from k (bounding radius ρ_m ≤ θ |c_m − c_k|, the
//! source side's rule, θ = 0.5 by default); each such m is one link, and every receiver left
//! uncovered keeps its own. It changes nothing and does not judge the accuracy of reading
//! one distance for a whole receiver node.
//!
//! In: a bundle folder with a hierarchical S, and optionally θ. Out: per translucent object,
//! its receiver patches, patch-to-node links, node-to-node links and patch links left, and
//! the ratio.
//!
//! ```sh
//! cargo run --release -p translux-engine --example receiver_cut -- BUNDLE_DIR [THETA]
//! ```

use std::path::PathBuf;
use std::process::ExitCode;

use glam::Vec3;
use translux_proto::bundle::Bundle;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(dir) = args.first().map(PathBuf::from) else {
        eprintln!("usage: receiver_cut BUNDLE_DIR [THETA]");
        return ExitCode::from(2);
    };
    let theta = match args.get(1).map(|a| a.parse::<f32>()) {
        None => 0.5,
        Some(Ok(t)) if t > 0.0 && t < 1.0 => t,
        Some(_) => {
            eprintln!("THETA must be a number between 0 and 1");
            return ExitCode::from(2);
        }
    };
    let bundle = match Bundle::open(&dir) {
        Ok(b) => b,
        Err(e) => {
            eprintln!("cannot open the bundle {}: {e}", dir.display());
            return ExitCode::FAILURE;
        }
    };
    let (Some(tree), true) = (bundle.tree(), bundle.manifest().subsurface.links > 0) else {
        eprintln!("the bundle's S is not hierarchical (no links)");
        return ExitCode::FAILURE;
    };
    let n = bundle.patch_areas().len();
    let m = tree.range.len();
    let corners = bundle.patch_corners();
    let area = bundle.patch_areas();
    // Each node's area-weighted centre and bounding radius over its patches' corners.
    let mut centre = vec![Vec3::ZERO; m];
    let mut radius = vec![0.0f32; m];
    for k in 0..m {
        let [a, b] = tree.range[k];
        let members = &tree.perm[a as usize..b as usize];
        let (mut c, mut w) = (Vec3::ZERO, 0.0f32);
        for &p in members {
            let t = corners[p as usize].map(Vec3::from);
            c += (t[0] + t[1] + t[2]) / 3.0 * area[p as usize];
            w += area[p as usize];
        }
        let c = if w > 0.0 { c / w } else { c };
        let r = members
            .iter()
            .flat_map(|&p| corners[p as usize])
            .map(|v| Vec3::from(v).distance(c))
            .fold(0.0f32, f32::max);
        (centre[k], radius[k]) = (c, r);
    }
    // Position of each patch in the tree's order; the nodes starting at each position,
    // widest first.
    let mut pos = vec![0u32; n];
    for (q, &p) in tree.perm.iter().enumerate() {
        pos[p as usize] = q as u32;
    }
    let mut starting: Vec<Vec<u32>> = vec![Vec::new(); n + 1];
    for k in 0..m {
        starting[tree.range[k][0] as usize].push(k as u32);
    }
    for s in &mut starting {
        s.sort_by_key(|&k| std::cmp::Reverse(tree.range[k as usize][1]));
    }
    // The receivers of each source node, by tree position.
    let d = bundle.distances();
    let mut receivers: Vec<Vec<u32>> = vec![Vec::new(); m];
    for (j, &q) in pos.iter().enumerate() {
        let (cols, _) = d.row(j);
        for &c in cols {
            if c as usize >= n {
                receivers[c as usize - n].push(q);
            }
        }
    }
    let objects = &bundle.manifest().objects;
    let patch_object = bundle.patch_objects();
    let mut per_object = vec![(0u64, 0u64, 0u64); objects.len()];
    for (k, js) in receivers.iter_mut().enumerate() {
        if js.is_empty() {
            continue;
        }
        js.sort_unstable();
        let o = patch_object[tree.perm[js[0] as usize] as usize] as usize;
        let entry = &mut per_object[o];
        entry.0 += js.len() as u64;
        // Walk the sorted positions: at each, the widest node starting there whose range
        // the run of consecutive receivers covers and which is small from k.
        let mut i = 0;
        while i < js.len() {
            let q = js[i] as usize;
            let mut run_end = i + 1;
            while run_end < js.len() && js[run_end] == js[run_end - 1] + 1 {
                run_end += 1;
            }
            let end = js[run_end - 1] as usize + 1;
            let taken = starting[q].iter().find(|&&r| {
                let r = r as usize;
                let [a, b] = tree.range[r];
                b - a > 1 && b as usize <= end && radius[r] <= theta * centre[r].distance(centre[k])
            });
            match taken {
                Some(&r) => {
                    let b = tree.range[r as usize][1] as usize;
                    entry.1 += 1;
                    i += b - q;
                }
                None => {
                    entry.2 += 1;
                    i += 1;
                }
            }
        }
    }
    println!("θ = {theta}\n");
    println!(
        "| object | patch → node links | node → node links | patch links left | links after / before |"
    );
    println!("|---|---|---|---|---|");
    let mut total = (0u64, 0u64, 0u64);
    for (o, &(before, nodes, left)) in per_object.iter().enumerate() {
        if before == 0 {
            continue;
        }
        total = (total.0 + before, total.1 + nodes, total.2 + left);
        println!(
            "| {} | {before} | {nodes} | {left} | {:.3} |",
            objects[o].name,
            (nodes + left) as f64 / before as f64
        );
    }
    println!(
        "| all | {} | {} | {} | {:.3} |",
        total.0,
        total.1,
        total.2,
        (total.1 + total.2) as f64 / total.0.max(1) as f64
    );
    ExitCode::SUCCESS
}
