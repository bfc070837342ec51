//! The memory budget across scenes: least-recently-used eviction, transparent reload.
//!
//! In: the bytes each resident scene holds (reported with [`MemoryBudget::charge`] under a
//! kind: `host` for the mapped bundle and the relight state and caches the server builds
//! from it, see [`crate::team::host_bytes`]; `gpu` for device buffers), each use of a scene
//! ([`MemoryBudget::touch`]) and the requests in flight on it ([`MemoryBudget::pin`]). Out:
//! which scenes to evict ([`MemoryBudget::victims`]): least recently used first, never one
//! that a request is using, until the total is within the limit. The server then drops the
//! evicted scenes' state (`SceneState::Evicted`) and reopens a scene on its next request,
//! without verifying checksums again ([`crate::team`]'s residency middleware).
//!
//! The GPU backend plugs in here: when it uploads a scene's matrices it calls
//! `charge(id, "gpu", bytes)`, and when a scene is evicted its device buffers go with the
//! dropped scene state. One limit covers all kinds (`--memory-budget`); a scene that alone is
//! larger than the limit is still served (the budget then holds just that scene).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Mutex, MutexGuard};

use translux_proto::api::SceneSummary;

/// What the server keeps of an evicted scene: where to reopen it from, and its summary for
/// `GET /api/v1/scenes`.
#[derive(Debug, Clone)]
pub struct EvictedScene {
    pub dir: PathBuf,
    pub summary: SceneSummary,
}

/// Bytes per kind for one scene, its last use and its requests in flight.
#[derive(Debug, Clone, Default)]
struct Resident {
    bytes: HashMap<&'static str, u64>,
    last_use: u64,
    pins: usize,
}

impl Resident {
    fn total(&self) -> u64 {
        self.bytes.values().sum()
    }
}

/// The accountant; `limit = None` accounts without ever evicting.
#[derive(Debug, Default)]
pub struct MemoryBudget {
    limit: Option<u64>,
    inner: Mutex<Inner>,
}

#[derive(Debug, Default)]
struct Inner {
    clock: u64,
    scenes: HashMap<String, Resident>,
    evictions: u64,
}

impl MemoryBudget {
    pub fn new(limit: Option<u64>) -> MemoryBudget {
        MemoryBudget {
            limit,
            inner: Mutex::new(Inner::default()),
        }
    }

    pub fn limit(&self) -> Option<u64> {
        self.limit
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Sets what scene `id` holds of `kind` (replacing the earlier figure).
    pub fn charge(&self, id: &str, kind: &'static str, bytes: u64) {
        let mut g = self.lock();
        g.clock += 1;
        let clock = g.clock;
        let r = g.scenes.entry(id.to_string()).or_default();
        r.bytes.insert(kind, bytes);
        if r.last_use == 0 {
            r.last_use = clock;
        }
    }

    /// Marks `id` as used now (if the budget knows it).
    pub fn touch(&self, id: &str) {
        let mut g = self.lock();
        g.clock += 1;
        let clock = g.clock;
        if let Some(r) = g.scenes.get_mut(id) {
            r.last_use = clock;
        }
    }

    /// A request starts using `id` (it cannot be evicted until [`MemoryBudget::unpin`]).
    pub fn pin(&self, id: &str) {
        let mut g = self.lock();
        g.clock += 1;
        let clock = g.clock;
        let r = g.scenes.entry(id.to_string()).or_default();
        r.pins += 1;
        r.last_use = clock;
    }

    /// The request using `id` ended. An entry that holds no bytes and no pins is dropped, so
    /// the table never outgrows the scenes that are resident or in use.
    pub fn unpin(&self, id: &str) {
        let mut g = self.lock();
        if let Some(r) = g.scenes.get_mut(id) {
            r.pins = r.pins.saturating_sub(1);
            if r.pins == 0 && r.total() == 0 {
                g.scenes.remove(id);
            }
        }
    }

    /// Scenes the table holds (resident, or pinned by a request in flight).
    pub fn tracked(&self) -> usize {
        self.lock().scenes.len()
    }

    /// Scene `id` is no longer resident (evicted, deleted): its bytes are no longer counted.
    pub fn forget(&self, id: &str) {
        let mut g = self.lock();
        if let Some(r) = g.scenes.get_mut(id) {
            r.bytes.clear();
            if r.pins == 0 {
                g.scenes.remove(id);
            }
        }
    }

    /// Bytes counted now, over every scene and kind.
    pub fn used(&self) -> u64 {
        self.lock().scenes.values().map(Resident::total).sum()
    }

    /// Scenes evicted so far.
    pub fn evictions(&self) -> u64 {
        self.lock().evictions
    }

    /// The scenes to evict, least recently used first, so that the rest fit the limit;
    /// pinned scenes and `keep` are never chosen. Their bytes stop counting at once (the
    /// caller drops them).
    pub fn victims(&self, keep: &str) -> Vec<String> {
        let Some(limit) = self.limit else {
            return Vec::new();
        };
        let mut g = self.lock();
        let mut used: u64 = g.scenes.values().map(Resident::total).sum();
        if used <= limit {
            return Vec::new();
        }
        let mut candidates: Vec<(u64, String, u64)> = g
            .scenes
            .iter()
            .filter(|(id, r)| r.pins == 0 && id.as_str() != keep && r.total() > 0)
            .map(|(id, r)| (r.last_use, id.clone(), r.total()))
            .collect();
        candidates.sort();
        let mut out = Vec::new();
        for (_, id, bytes) in candidates {
            if used <= limit {
                break;
            }
            used -= bytes;
            g.scenes.remove(&id);
            g.evictions += 1;
            out.push(id);
        }
        out
    }
}

/// `8GiB`, `512 MiB`, `1.5G`, `100000000` → bytes (binary units; `k`, `M`, `G`, `T` with an
/// optional `i` and `B`).
pub fn parse_bytes(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let value: f64 = num
        .parse()
        .map_err(|_| format!("{text:?} is not a size such as 512MiB or 8GiB"))?;
    let scale: f64 = match unit
        .trim()
        .trim_end_matches(['B', 'b'])
        .trim_end_matches('i')
    {
        "" => 1.0,
        "k" | "K" => 1024.0,
        "M" | "m" => 1024.0 * 1024.0,
        "G" | "g" => 1024.0 * 1024.0 * 1024.0,
        "T" | "t" => 1024.0 * 1024.0 * 1024.0 * 1024.0,
        _ => {
            return Err(format!(
                "{text:?}: unknown unit {unit:?} (use B, KiB, MiB, GiB, TiB)"
            ));
        }
    };
    let bytes = value * scale;
    if !(1.0..1.8e19).contains(&bytes) {
        return Err(format!("{text:?} is out of range"));
    }
    Ok(bytes as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evicts_least_recently_used_first_never_pinned() {
        let b = MemoryBudget::new(Some(250));
        b.charge("a", "host", 100);
        b.charge("b", "host", 100);
        b.touch("a");
        b.charge("c", "host", 100);
        // 300 > 250: b is the least recently used.
        assert_eq!(b.victims("c"), vec!["b".to_string()]);
        assert_eq!(b.used(), 200);
        // A GPU charge on c pushes over again; a is pinned, c kept: nothing to evict.
        b.pin("a");
        b.charge("c", "gpu", 100);
        assert_eq!(b.victims("c"), Vec::<String>::new());
        assert_eq!(b.used(), 300);
        b.unpin("a");
        assert_eq!(b.victims("c"), vec!["a".to_string()]);
        assert_eq!(b.used(), 200);
        assert_eq!(b.evictions(), 2);
        // A scene larger than the limit on its own stays.
        b.charge("huge", "host", 1000);
        assert_eq!(b.victims("huge"), vec!["c".to_string()]);
        b.forget("huge");
        assert_eq!(b.used(), 0);
        // No limit: never evicts.
        let free = MemoryBudget::new(None);
        free.charge("a", "host", u64::MAX / 4);
        free.charge("b", "host", u64::MAX / 4);
        assert!(free.victims("a").is_empty());
    }

    /// Requests for ids that hold nothing (made-up ids from an attacker) must not grow the
    /// table that every eviction scans.
    #[test]
    fn unknown_scene_ids_do_not_leak_budget_entries() {
        let b = MemoryBudget::new(Some(1000));
        b.charge("real", "host", 100);
        for k in 0..10_000 {
            let id = format!("nope{k}");
            b.pin(&id);
            b.touch(&id);
            b.unpin(&id);
            b.touch(&format!("other{k}"));
        }
        assert_eq!(b.tracked(), 1);
        // A real scene pinned twice stays until both requests end, and keeps its bytes.
        b.pin("real");
        b.pin("real");
        b.unpin("real");
        b.unpin("real");
        assert_eq!((b.tracked(), b.used()), (1, 100));
    }

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_bytes("100"), Ok(100));
        assert_eq!(parse_bytes("1KiB"), Ok(1024));
        assert_eq!(parse_bytes("512MiB"), Ok(512 << 20));
        assert_eq!(parse_bytes("8G"), Ok(8 << 30));
        assert_eq!(parse_bytes("1.5GiB"), Ok(3 << 29));
        assert!(parse_bytes("lots").is_err());
        assert!(parse_bytes("5 parsecs").is_err());
        assert!(parse_bytes("0").is_err());
    }
}
