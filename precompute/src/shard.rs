//! A precompute split into shards that run anywhere (a Slurm job array, a Kubernetes
//! Indexed Job, several shells) and a merge that puts them together.
//!
//! In: a [`Shard`] (`I/K`: the I-th of K equal shares of the receiver rows, 0-based) and the
//! rows the pipeline computed for it ([`ShardRows`]: the hierarchical F's row block, the
//! environment visibility of the same patches, and the subsurface cuts of its share of the
//! translucent receivers). Out: a part folder `DIR.parts/part-I-of-K/`
//! — `part.json` (which share, the plan it was made for, each file's length and xxh3
//! checksum, the counts and times) beside the raw little-endian arrays — written to a hidden
//! temporary folder and renamed into place, so a killed shard leaves nothing that looks
//! whole. [`read_parts`] checks all K parts against the merge's own plan and gives the rows
//! back in order; the pipeline then runs the remaining stages and writes the bundle.
//!
//! The plan ([`plan_hash`]) fingerprints what the rows depend on: the patches, the source
//! triangles, the cluster tree, the F, environment and subsurface settings and the
//! materials. Each receiver's row depends on nothing else, so the merged arrays are the
//! bytes a one-box precompute writes.
//!
//! What is sharded: the form factors and the environment visibility (the stages that cast
//! rays per receiver), and of a hierarchical S the cut of every receiver whose optical
//! distances are traced on demand (`crate::slinks::shard_cuts`: its direct sources and
//! links, the distance runs they need and the links' spreads — most of the subsurface
//! stage). Those receivers are split apart from F's rows: the receivers of every object
//! traced on demand, one after the other, in K equal shares, so that each shard gets an
//! equal share of S's work whatever the diffuse patches around them (F's row split would
//! give the translucent patches to whichever shards their objects' indices fall in). Each
//! shard builds the oracles (voxel grids) of those objects itself. In the merge: the
//! oracles again (their stats go into the manifest), the rows of S put together from the
//! cuts, S's assembly, and whatever is not cut on demand — a pairwise S's distances, thin
//! sheets, heterogeneous objects and the random walks of simulated objects (per object,
//! not per receiver) — and T. Parts of version 1 (before the cuts) are refused.

use std::io::Write;
use std::ops::Range;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use translux_proto::bundle::EnvironmentInfo;

use crate::hierarchy::RowBlock;
use crate::slinks::ReceiverCuts;

/// The I-th (0-based) of K shares of a precompute's receiver rows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    pub index: u32,
    pub count: u32,
}

/// The most shards a precompute is split into.
pub const MAX_SHARDS: u32 = 4096;

impl std::str::FromStr for Shard {
    type Err = String;

    /// `I/K` with 0 ≤ I < K ≤ [`MAX_SHARDS`].
    fn from_str(s: &str) -> Result<Self, String> {
        let (i, k) = s
            .split_once('/')
            .ok_or_else(|| format!("'{s}' is not I/K (e.g. 0/4: the first of four shards)"))?;
        let index: u32 = i
            .trim()
            .parse()
            .map_err(|_| format!("'{s}': the shard index '{i}' is not a whole number"))?;
        let count = parse_count(k.trim()).map_err(|e| format!("'{s}': {e}"))?;
        if index >= count {
            return Err(format!(
                "'{s}': shards are numbered from 0 to {} (the index must be below the count)",
                count - 1
            ));
        }
        Ok(Shard { index, count })
    }
}

/// A shard count: 1 to [`MAX_SHARDS`].
pub fn parse_count(k: &str) -> Result<u32, String> {
    let count: u32 = k
        .parse()
        .map_err(|_| format!("the shard count '{k}' is not a whole number"))?;
    if !(1..=MAX_SHARDS).contains(&count) {
        return Err(format!(
            "the shard count must be 1 to {MAX_SHARDS}, got {count}"
        ));
    }
    Ok(count)
}

impl Shard {
    /// The receiver rows of this shard among `n`: K nearly equal consecutive ranges.
    pub fn rows(&self, n: usize) -> Range<usize> {
        let at = |i: u32| (n as u128 * i as u128 / self.count as u128) as usize;
        at(self.index)..at(self.index + 1)
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// How much of a precompute one run does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Split {
    /// Every stage, one bundle (one box).
    #[default]
    Whole,
    /// One shard's rows into `DIR.parts/`.
    Shard(Shard),
    /// The K parts in `DIR.parts/` put together, the remaining stages, the bundle.
    Merge(u32),
}

/// The rows of F and the environment visibility that one run computed.
#[derive(Debug, Clone, Default)]
pub struct ShardRows {
    pub block: RowBlock,
    /// Half-float visibility of the block's patches (`[rows · bins]`) and its summary.
    pub environment: Option<(Vec<u16>, EnvironmentInfo)>,
    /// The cuts of the shard's share of the receivers a hierarchical S traces on demand
    /// (none without such an S).
    pub cuts: ReceiverCuts,
    /// Seconds of the form-factor, environment and subsurface stages.
    pub form_factor_seconds: f64,
    pub environment_seconds: f64,
    pub subsurface_seconds: f64,
}

/// What [`write_part`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct PartReport {
    pub shard: Shard,
    pub dir: PathBuf,
    pub rows: Range<usize>,
    /// `false`: the part was already there, finished, for the same plan (nothing was done).
    pub computed: bool,
    pub bytes: u64,
    pub entries: u64,
    pub form_factor_seconds: f64,
    pub environment_seconds: f64,
    pub subsurface_seconds: f64,
}

/// The folder of a bundle's parts: `DIR.parts` beside `DIR`.
pub fn parts_dir(out: &Path) -> PathBuf {
    let mut name = out
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_else(|| "bundle".into());
    name.push(".parts");
    out.with_file_name(name)
}

/// The folder of one finished part.
pub fn part_dir(out: &Path, shard: Shard) -> PathBuf {
    parts_dir(out).join(part_name(shard))
}

fn part_name(shard: Shard) -> String {
    format!("part-{}-of-{}", shard.index, shard.count)
}

const PART_FORMAT: &str = "translux-part";
/// 2: the subsurface cuts of the shard's receivers (the `s_cut_*` arrays).
const PART_VERSION: u32 = 2;
const HEADER: &str = "part.json";
const FILES: [&str; 7] = [
    "c_row_ptr.u64",
    "c_col.u32",
    "c_val.f32",
    "env_visibility.f16",
    "s_cut_ptr.u64",
    "s_cut_direct.u32",
    "s_cut_entry.u32x4",
];

/// `part.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Header {
    format: String,
    version: u32,
    index: u32,
    count: u32,
    first_row: u64,
    rows: u64,
    /// [`plan_hash`] of the run that made it, hex.
    plan: String,
    created_by: String,
    /// `(name, bytes, xxh3 hex)` of each array file.
    files: Vec<(String, u64, String)>,
    rays: u64,
    tests: u64,
    node_entries: u64,
    patch_entries: u64,
    covered: u64,
    environment: Option<EnvironmentInfo>,
    form_factor_seconds: f64,
    environment_seconds: f64,
    /// Version 2 on (an older part's header reads, to be refused by its version).
    #[serde(default)]
    cut_first: u64,
    #[serde(default)]
    cut_node_runs: (u64, u64),
    #[serde(default)]
    subsurface_seconds: f64,
}

/// The fingerprint of what a shard's rows depend on, from the caller's byte views of the
/// patches, source triangles, tree and settings (in a fixed order).
pub fn plan_hash(pieces: &[&[u8]]) -> u64 {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    for p in pieces {
        h.update(&(p.len() as u64).to_le_bytes());
        h.update(p);
    }
    h.digest()
}

/// Whether `DIR.parts/part-I-of-K` is already finished for this plan (`Ok(true)`), absent
/// (`Ok(false)`), or there but made for another plan or damaged (an error naming it).
pub fn finished(out: &Path, shard: Shard, plan: u64) -> Result<bool, String> {
    let dir = part_dir(out, shard);
    if !dir.exists() {
        return Ok(false);
    }
    read_part(&dir, shard, plan)
        .map(|_| true)
        .map_err(|e| format!("{e}; remove {} to compute the shard again", dir.display()))
}

/// Writes shard `shard`'s rows as `DIR.parts/part-I-of-K` (atomically: a hidden temporary
/// folder renamed into place).
pub fn write_part(
    out: &Path,
    shard: Shard,
    plan: u64,
    rows: &ShardRows,
) -> Result<PartReport, String> {
    let parts = parts_dir(out);
    std::fs::create_dir_all(&parts)
        .map_err(|e| format!("cannot create {}: {e}", parts.display()))?;
    remove_own_leftovers(&parts, shard);
    let dir = part_dir(out, shard);
    let tmp = parts.join(format!(
        ".{}.tmp-{}-{}",
        part_name(shard),
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos())
    ));
    let written = write_files(&tmp, shard, plan, rows).and_then(|bytes| {
        std::fs::rename(&tmp, &dir)
            .map_err(|e| format!("cannot rename {} to {}: {e}", tmp.display(), dir.display()))
            .map(|()| bytes)
    });
    let bytes = match written {
        Ok(b) => b,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            // Another run of the same shard may have finished first: that part stands.
            if finished(out, shard, plan) == Ok(true) {
                0
            } else {
                return Err(e);
            }
        }
    };
    Ok(PartReport {
        shard,
        dir,
        rows: rows.block.first as usize..rows.block.first as usize + rows.block.rows(),
        computed: true,
        bytes,
        entries: rows.block.col.len() as u64,
        form_factor_seconds: rows.form_factor_seconds,
        environment_seconds: rows.environment_seconds,
        subsurface_seconds: rows.subsurface_seconds,
    })
}

/// Earlier temporaries of this shard (a killed run of it): removed before it writes again.
/// Only this shard's, so parallel shards never touch each other's.
fn remove_own_leftovers(parts: &Path, shard: Shard) {
    let prefix = format!(".{}.tmp-", part_name(shard));
    let Ok(entries) = std::fs::read_dir(parts) else {
        return;
    };
    for e in entries.flatten() {
        if e.file_name().to_string_lossy().starts_with(&prefix) {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// The array files and `part.json` (last, after every array is synced) in `tmp`; their bytes.
fn write_files(tmp: &Path, shard: Shard, plan: u64, rows: &ShardRows) -> Result<u64, String> {
    std::fs::create_dir(tmp).map_err(|e| format!("cannot create {}: {e}", tmp.display()))?;
    let env_bits: &[u16] = rows.environment.as_ref().map_or(&[], |e| &e.0);
    let arrays: [&[u8]; 7] = [
        bytemuck::cast_slice(&rows.block.row_ptr),
        bytemuck::cast_slice(&rows.block.col),
        bytemuck::cast_slice(&rows.block.val),
        bytemuck::cast_slice(env_bits),
        bytemuck::cast_slice(&rows.cuts.ptr),
        bytemuck::cast_slice(&rows.cuts.direct),
        bytemuck::cast_slice(&rows.cuts.entries),
    ];
    let mut files = Vec::new();
    let mut total = 0u64;
    for (name, data) in FILES.iter().zip(arrays) {
        write_synced(&tmp.join(name), data)?;
        total += data.len() as u64;
        files.push((
            name.to_string(),
            data.len() as u64,
            format!("{:016x}", xxhash_rust::xxh3::xxh3_64(data)),
        ));
    }
    let b = &rows.block;
    let header = Header {
        format: PART_FORMAT.into(),
        version: PART_VERSION,
        index: shard.index,
        count: shard.count,
        first_row: b.first,
        rows: b.rows() as u64,
        plan: format!("{plan:016x}"),
        created_by: format!("translux-precompute {}", env!("CARGO_PKG_VERSION")),
        files,
        rays: b.rays,
        tests: b.tests,
        node_entries: b.node_entries,
        patch_entries: b.patch_entries,
        covered: b.covered,
        environment: rows.environment.as_ref().map(|e| e.1.clone()),
        form_factor_seconds: rows.form_factor_seconds,
        environment_seconds: rows.environment_seconds,
        cut_first: rows.cuts.first,
        cut_node_runs: rows.cuts.node_runs,
        subsurface_seconds: rows.subsurface_seconds,
    };
    let text = serde_json::to_vec_pretty(&header).map_err(|e| e.to_string())?;
    write_synced(&tmp.join(HEADER), &text)?;
    Ok(total + text.len() as u64)
}

fn write_synced(path: &Path, data: &[u8]) -> Result<(), String> {
    let mut f = std::fs::File::create(path)
        .map_err(|e| format!("cannot create {}: {e}", path.display()))?;
    f.write_all(data)
        .and_then(|()| f.sync_all())
        .map_err(|e| format!("cannot write {}: {e}", path.display()))
}

/// One part read back and checked: its header says it is `shard` of this plan, and every
/// file has the length and checksum the header records.
fn read_part(dir: &Path, shard: Shard, plan: u64) -> Result<ShardRows, String> {
    let what = format!(
        "part {} of {} ({})",
        shard.index,
        shard.count,
        dir.display()
    );
    let text = std::fs::read(dir.join(HEADER))
        .map_err(|e| format!("{what} has no readable {HEADER}: {e}"))?;
    let h: Header = serde_json::from_slice(&text)
        .map_err(|e| format!("{what}: {HEADER} is not a part header: {e}"))?;
    if h.format != PART_FORMAT || h.version != PART_VERSION {
        return Err(format!(
            "{what} is a {} version {} part; this precompute reads {PART_FORMAT} version \
             {PART_VERSION}",
            h.format, h.version
        ));
    }
    if (h.index, h.count) != (shard.index, shard.count) {
        return Err(format!(
            "{what} holds shard {}/{} (a copied or renamed part): its rows would be counted \
             twice",
            h.index, h.count
        ));
    }
    if h.plan != format!("{plan:016x}") {
        return Err(format!(
            "{what} was computed for another scene or other settings (its plan {}, this \
             one {plan:016x})",
            h.plan
        ));
    }
    let mut data = Vec::new();
    for name in FILES {
        let Some((_, len, sum)) = h.files.iter().find(|f| f.0 == name) else {
            return Err(format!("{what}: {HEADER} does not list {name}"));
        };
        let bytes = std::fs::read(dir.join(name))
            .map_err(|e| format!("{what}: cannot read {name}: {e}"))?;
        if bytes.len() as u64 != *len {
            return Err(format!(
                "{what}: {name} is {} bytes, its header says {len} (truncated?)",
                bytes.len()
            ));
        }
        if format!("{:016x}", xxhash_rust::xxh3::xxh3_64(&bytes)) != *sum {
            return Err(format!(
                "{what}: {name} does not match its checksum (damaged)"
            ));
        }
        data.push(bytes);
    }
    let cast_err = |name: &str| format!("{what}: {name} has a length that is not whole items");
    let row_ptr: Vec<u64> = items(&data[0]).ok_or_else(|| cast_err(FILES[0]))?;
    let col: Vec<u32> = items(&data[1]).ok_or_else(|| cast_err(FILES[1]))?;
    let val: Vec<f32> = items(&data[2]).ok_or_else(|| cast_err(FILES[2]))?;
    let env: Vec<u16> = items(&data[3]).ok_or_else(|| cast_err(FILES[3]))?;
    let cuts = ReceiverCuts {
        first: h.cut_first,
        ptr: items(&data[4]).ok_or_else(|| cast_err(FILES[4]))?,
        direct: items(&data[5]).ok_or_else(|| cast_err(FILES[5]))?,
        entries: items(&data[6]).ok_or_else(|| cast_err(FILES[6]))?,
        node_runs: h.cut_node_runs,
    };
    if row_ptr.len() as u64 != h.rows + 1
        || row_ptr.last().copied() != Some(col.len() as u64)
        || col.len() != val.len()
    {
        return Err(format!("{what}: its row offsets do not match its entries"));
    }
    if !cuts.is_consistent() {
        return Err(format!(
            "{what}: its subsurface cuts' offsets do not match their entries"
        ));
    }
    Ok(ShardRows {
        block: RowBlock {
            first: h.first_row,
            row_ptr,
            col,
            val,
            rays: h.rays,
            tests: h.tests,
            node_entries: h.node_entries,
            patch_entries: h.patch_entries,
            covered: h.covered,
        },
        environment: h.environment.map(|info| (env, info)),
        cuts,
        form_factor_seconds: h.form_factor_seconds,
        environment_seconds: h.environment_seconds,
        subsurface_seconds: h.subsurface_seconds,
    })
}

/// Little-endian items from bytes read from a file (copied: a file's buffer need not be
/// aligned for `T`); `None` when the length is not whole items.
fn items<T: bytemuck::Pod>(bytes: &[u8]) -> Option<Vec<T>> {
    let size = std::mem::size_of::<T>();
    if !bytes.len().is_multiple_of(size) {
        return None;
    }
    let mut out = vec![T::zeroed(); bytes.len() / size];
    bytemuck::cast_slice_mut::<T, u8>(&mut out).copy_from_slice(bytes);
    Some(out)
}

/// Every part of a split into `count` for `n` receivers, checked: none missing, none from
/// another split or another plan, none damaged, each covering the rows its index gives.
pub fn read_parts(
    out: &Path,
    count: u32,
    plan: u64,
    n: usize,
    rerun: &dyn Fn(Shard) -> String,
) -> Result<Vec<ShardRows>, String> {
    let parts = parts_dir(out);
    refuse_other_splits(&parts, count)?;
    let mut rows = Vec::with_capacity(count as usize);
    for index in 0..count {
        let shard = Shard { index, count };
        let dir = part_dir(out, shard);
        if !dir.is_dir() {
            return Err(format!(
                "part {index} of {count} is missing ({}): run `{}` first",
                dir.display(),
                rerun(shard)
            ));
        }
        let r = read_part(&dir, shard, plan)?;
        let want = shard.rows(n);
        if r.block.first as usize != want.start || r.block.rows() != want.len() {
            return Err(format!(
                "part {index} of {count} ({}) holds rows {}..{}; shard {shard} of {n} patches \
                 is rows {}..{}",
                dir.display(),
                r.block.first,
                r.block.first as usize + r.block.rows(),
                want.start,
                want.end
            ));
        }
        let next: u64 = rows
            .iter()
            .map(|p: &ShardRows| p.cuts.receivers() as u64)
            .sum();
        if r.cuts.first != next {
            return Err(format!(
                "part {index} of {count} ({}) holds the subsurface cuts of receivers from {}; \
                 the parts before it end at {next}",
                dir.display(),
                r.cuts.first
            ));
        }
        rows.push(r);
    }
    Ok(rows)
}

/// A part of a split into another count beside this one would hold some rows twice.
fn refuse_other_splits(parts: &Path, count: u32) -> Result<(), String> {
    let Ok(entries) = std::fs::read_dir(parts) else {
        return Ok(());
    };
    let mut names: Vec<String> = entries
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    for name in names {
        let Some(k) = name
            .strip_prefix("part-")
            .and_then(|r| r.split_once("-of-"))
            .map(|(_, k)| k)
        else {
            continue;
        };
        if k != count.to_string() {
            return Err(format!(
                "{} holds {name}, a part of a split into {k}, beside the {count} parts being \
                 merged: their rows would be counted twice; remove it (or merge {k})",
                parts.display()
            ));
        }
    }
    Ok(())
}

/// Removes `DIR.parts` once the bundle is written.
pub fn remove_parts(out: &Path) {
    let _ = std::fs::remove_dir_all(parts_dir(out));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_parse_and_cover_the_rows() {
        let s: Shard = "2/4".parse().unwrap();
        assert_eq!(s, Shard { index: 2, count: 4 });
        for bad in ["4/4", "1", "a/2", "0/0", "0/5000", "-1/2"] {
            assert!(bad.parse::<Shard>().is_err(), "{bad}");
        }
        let n = 1001;
        let mut next = 0;
        for index in 0..7 {
            let r = Shard { index, count: 7 }.rows(n);
            assert_eq!(r.start, next);
            next = r.end;
        }
        assert_eq!(next, n);
    }

    fn rows(first: u64, k: usize) -> ShardRows {
        ShardRows {
            block: RowBlock {
                first,
                row_ptr: (0..=k as u64).collect(),
                col: (0..k as u32).collect(),
                val: vec![0.5; k],
                rays: 7,
                ..Default::default()
            },
            // A receiver of the cuts per row: one direct source and one link each.
            cuts: ReceiverCuts {
                first,
                ptr: (0..=k as u64).map(|r| 2 * r).collect(),
                direct: vec![1; k],
                entries: (0..k as u32)
                    .flat_map(|r| [[r, 1.5f32.to_bits(), 0, 0], [r, 2.5f32.to_bits(), 0, 7]])
                    .collect(),
                node_runs: (1, 0),
            },
            ..Default::default()
        }
    }

    #[test]
    fn parts_round_trip_and_are_refused_when_missing_foreign_duplicated_or_damaged() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("scene");
        let n = 10;
        let rerun = |s: Shard| format!("--shard {s}");
        for index in 0..2 {
            let s = Shard { index, count: 2 };
            let r = s.rows(n);
            assert!(!finished(&out, s, 1).unwrap());
            write_part(&out, s, 1, &rows(r.start as u64, r.len())).unwrap();
            assert!(finished(&out, s, 1).unwrap());
        }
        let back = read_parts(&out, 2, 1, n, &rerun).unwrap();
        assert_eq!(back[1].block.first, 5);
        assert_eq!(back[1].block.rays, 7);
        assert_eq!(back[1].cuts, rows(5, 5).cuts);

        // A part of the format before the subsurface cuts: refused by its version.
        let header = parts_dir(&out).join("part-1-of-2").join(HEADER);
        let text = std::fs::read_to_string(&header).unwrap();
        let mut old: serde_json::Value = serde_json::from_str(&text).unwrap();
        let o = old.as_object_mut().unwrap();
        for new in ["cut_first", "cut_node_runs", "subsurface_seconds"] {
            o.remove(new);
        }
        o.insert("version".into(), 1.into());
        std::fs::write(&header, serde_json::to_vec(&old).unwrap()).unwrap();
        let e = read_parts(&out, 2, 1, n, &rerun).unwrap_err();
        assert!(
            e.contains("part 1 of 2") && e.contains("version 1") && e.contains("version 2"),
            "{e}"
        );
        std::fs::write(&header, text).unwrap();
        // Cuts that do not follow on from the part before.
        std::fs::remove_dir_all(parts_dir(&out).join("part-1-of-2")).unwrap();
        let mut gap = rows(5, 5);
        gap.cuts.first = 6;
        write_part(&out, Shard { index: 1, count: 2 }, 1, &gap).unwrap();
        let e = read_parts(&out, 2, 1, n, &rerun).unwrap_err();
        assert!(e.contains("subsurface cuts of receivers from 6"), "{e}");
        std::fs::remove_dir_all(parts_dir(&out).join("part-1-of-2")).unwrap();
        write_part(&out, Shard { index: 1, count: 2 }, 1, &rows(5, 5)).unwrap();

        // Another plan.
        let e = read_parts(&out, 2, 2, n, &rerun).unwrap_err();
        assert!(e.contains("another scene or other settings"), "{e}");
        assert!(finished(&out, Shard { index: 0, count: 2 }, 2).is_err());
        // Missing.
        let e = read_parts(&out, 3, 1, n, &rerun).unwrap_err();
        assert!(e.contains("part-0-of-2, a part of a split into 2"), "{e}");
        // Duplicated: part 1's folder copied over part 0's.
        let parts = parts_dir(&out);
        std::fs::remove_dir_all(parts.join("part-0-of-2")).unwrap();
        let e = read_parts(&out, 2, 1, n, &rerun).unwrap_err();
        assert!(
            e.contains("part 0 of 2 is missing") && e.contains("--shard 0/2"),
            "{e}"
        );
        copy_dir(&parts.join("part-1-of-2"), &parts.join("part-0-of-2"));
        let e = read_parts(&out, 2, 1, n, &rerun).unwrap_err();
        assert!(e.contains("holds shard 1/2"), "{e}");
        // Damaged.
        std::fs::remove_dir_all(parts.join("part-0-of-2")).unwrap();
        write_part(&out, Shard { index: 0, count: 2 }, 1, &rows(0, 5)).unwrap();
        std::fs::write(parts.join("part-1-of-2").join("c_val.f32"), [0u8; 20]).unwrap();
        let e = read_parts(&out, 2, 1, n, &rerun).unwrap_err();
        assert!(e.contains("c_val.f32 does not match its checksum"), "{e}");
        std::fs::write(parts.join("part-1-of-2").join("c_val.f32"), [0u8; 3]).unwrap();
        let e = read_parts(&out, 2, 1, n, &rerun).unwrap_err();
        assert!(e.contains("truncated"), "{e}");
    }

    fn copy_dir(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap().flatten() {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}
