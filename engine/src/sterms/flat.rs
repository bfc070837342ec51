//! One object's radial terms as flat arrays of plain records, for a device that writes the
//! object's rows of S itself on a translucency change (the server's GPU backend).
//!
//! In: an [`ObjectTerms`], where its rows sit in the scene's S ([`Placement`] and S's row
//! pointers), and the patches' areas. Out: [`FlatTerms`], the same entries, terms and links
//! [`ObjectTerms::write`] reads, and the two gathers its energy bound sums through; and
//! [`FlatTable`], a profile's cells as [`TermTable`] lays them out. A device writes the
//! object's values into an array of its own (its rows of S in S's order, entries then
//! links), sums the columns' and the linked nodes' energies through the gathers, takes
//! the bound's factors from [`ObjectTerms::factors_from_sums`] and scales the values by
//! them: the same S as `write` makes, to f32 rounding (the sums are added in another order).

use super::{ObjectTerms, Placement, TermTable};
use bytemuck::{Pod, Zeroable};

/// Bit 31 of a record's flag word: the entry or link is read through the other table (a
/// sheet's transmittance).
pub const OPPOSITE: u32 = 1 << 31;
/// Bit 30 of a link's flag word: it is read at two roots, the mean of R at both.
pub const TWO: u32 = 1 << 30;

/// One row of the object's S: a patch's (its direct entries, then its links) or a node
/// row's (links alone). 32 bytes.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct FlatRow {
    /// The row's first value in the object's value array.
    pub value: u32,
    /// Its entries, `entries[0]..entries[1]` of [`FlatTerms::entries`].
    pub entries: [u32; 2],
    /// Its links, `links[0]..links[1]` of [`FlatTerms::links`].
    pub links: [u32; 2],
    /// The patch's local index (the self term's source), `u32::MAX` for a node row.
    pub local: u32,
    /// The receiver's area (the patch's, or the node's).
    pub area: f32,
    pub _pad: u32,
}

/// One stored entry. 16 bytes; the entry's terms end where the next entry's start (the
/// array ends with one entry more than there are, which holds only that end).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct FlatEntry {
    /// Its source patch (local index).
    pub src: u32,
    /// Its optical distance.
    pub dist: f32,
    /// The largest √r its R terms stand for.
    pub hi_max: f32,
    /// Its first term; [`OPPOSITE`] set for a sheet's other side.
    pub terms: u32,
}

/// One link to a cluster node. 32 bytes.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct FlatLink {
    /// √r, and the two roots it is read at with [`TWO`].
    pub root: f32,
    pub two: [f32; 2],
    /// The node's area A_k (the link's value is A_k R).
    pub area: f32,
    /// The linked node, counted from the object's first ([`FlatTerms::nodes`]), with
    /// [`OPPOSITE`] and [`TWO`].
    pub node: u32,
    /// The link's value in the object's value array.
    pub value: u32,
    pub _pad: [u32; 2],
}

impl FlatLink {
    /// The linked node, counted from the object's first (its flags left out).
    pub fn node_index(&self) -> usize {
        (self.node & !(OPPOSITE | TWO)) as usize
    }
}

/// Where a run of the object's values sits in the scene's S.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ValueRun {
    /// The run's first value in S's value array.
    pub s_value: u64,
    /// Its first in the object's value array.
    pub local: u32,
    pub len: u32,
}

/// One object's terms flattened ([`ObjectTerms::flatten`]).
#[derive(Debug, Clone, Default)]
pub struct FlatTerms {
    /// The object's patch rows (local order), then its node rows.
    pub rows: Vec<FlatRow>,
    /// Every entry, and one more holding the last one's end of terms.
    pub entries: Vec<FlatEntry>,
    /// Every term as (√r, negated for W; weight; the cell's `lo`, `hi`).
    pub terms: Vec<[f32; 4]>,
    pub links: Vec<FlatLink>,
    /// Column i's entries (local patch i) are `column_items[column_ptr[i]..column_ptr[i +
    /// 1]]`, each as (its value, the receiver's area as f32 bits): Σ A_j S_ji is their sum.
    pub column_ptr: Vec<u32>,
    pub column_items: Vec<[u32; 2]>,
    /// Linked node k's links are `node_items[node_ptr[k]..node_ptr[k + 1]]`, each as (the
    /// link, the receiver's area as f32 bits): e_k = Σ A_j R(r_jk) is their sum.
    pub node_ptr: Vec<u32>,
    pub node_items: Vec<[u32; 2]>,
    /// Values in the object's value array.
    pub values: usize,
    /// Where they go in S.
    pub runs: Vec<ValueRun>,
    /// Patches (local columns) and linked nodes.
    pub n: usize,
    pub nodes: usize,
    /// With node rows pushed down to the patches ([`ObjectTerms::push_into`]): each value
    /// of the object's rows of the pushed S is the sum of
    /// `push_items[push_ptr[e]..push_ptr[e + 1]]`'s values, and `runs` place the pushed
    /// values (`pushed` of them) in S. Empty without node rows: `runs` place the values.
    pub push_ptr: Vec<u32>,
    pub push_items: Vec<u32>,
    pub pushed: usize,
}

/// A profile's table as [`TermTable`] reads it: R's cells, a zero cell, W's cells and W's
/// total, each as its start and its rise over the cell (RGB in lanes 0–2).
#[derive(Debug, Clone)]
pub struct FlatTable {
    pub cells: Vec<[[f32; 4]; 2]>,
    /// √ of its radius: a term's cell ends inside the table below it.
    pub end: f32,
    /// Its radius (an entry at least this far is not kept).
    pub r_max: f32,
    /// Cells per unit of √r, and R's count of cells N.
    pub scale: f32,
    pub cells_f: f32,
    /// Where W's cells start (N + 1).
    pub w_base: u32,
}

impl FlatTable {
    /// `t`'s cells and bounds.
    pub fn of(t: &TermTable<'_>) -> FlatTable {
        FlatTable {
            cells: t
                .cells
                .iter()
                .map(|[a, b]| [a.to_array(), b.to_array()])
                .collect(),
            end: t.end,
            r_max: t.r_max(),
            scale: t.scale,
            cells_f: t.cells_f,
            w_base: t.w_base as u32,
        }
    }
}

impl ObjectTerms {
    /// The object's entries, terms and links as flat records ([`FlatTerms`]), its rows
    /// placed by `at` in the scene's S of row pointers `s_row_ptr`; `area` is the object's
    /// patch areas. An error when S's rows are not laid out as [`ObjectTerms::pattern`]
    /// made them (S was built for other terms): the first such row of S.
    pub fn flatten(
        &self,
        area: &[f32],
        at: Placement<'_>,
        s_row_ptr: &[u64],
    ) -> Result<FlatTerms, usize> {
        let n = self.row_ptr.len() - 1;
        let mut f = FlatTerms {
            n,
            nodes: self.node_count(at),
            ..Default::default()
        };
        self.flat_entries(&mut f);
        let node_rows = if at.nodes.is_some() {
            self.recv.len()
        } else {
            0
        };
        // The patch rows, then the node rows: each row's entries, then its links.
        let mut value = 0u32;
        for j in 0..n + node_rows {
            let node_row = j >= n;
            let (set, l, entries, s_row, aj) = self.row_place(j, area, at);
            let links = match set.ptr.get(l..l + 2).filter(|_| at.nodes.is_some()) {
                Some(p) => p[0] as usize..p[1] as usize,
                None => 0..0,
            };
            let len = entries.len() + links.len();
            let s_len = match s_row_ptr.get(s_row..s_row + 2) {
                Some(p) => p[1] - p[0],
                None => u64::MAX,
            };
            if s_len != len as u64 {
                return Err(s_row);
            }
            let first_link = f.links.len() as u32;
            for (x, l) in links.enumerate() {
                f.links
                    .push(self.flat_link(set, l, at, value + entries.len() as u32 + x as u32));
            }
            f.rows.push(FlatRow {
                value,
                entries: [entries.start, entries.end],
                links: [first_link, f.links.len() as u32],
                local: if node_row { u32::MAX } else { j as u32 },
                area: aj,
                _pad: 0,
            });
            push_run(&mut f.runs, s_row_ptr[s_row], value, len as u32);
            value += len as u32;
        }
        f.values = value as usize;
        self.flat_gathers(&mut f);
        Ok(f)
    }

    /// `f` (flattened against S with its node rows) made to write S with those rows pushed
    /// down to the patches (`transport::push_node_rows`, `pushed` of N × (N + M)): each
    /// pushed value of the object's patch rows as the sum of the values it gathers, and
    /// `f.runs` placing them. Nothing changes without node rows. An error (the first row of
    /// S that differs) when `pushed`'s rows are not the object's rows with its node rows
    /// added (another object's node row reaches its patches, or S was pushed from other
    /// terms).
    pub fn push_into(
        &self,
        f: &mut FlatTerms,
        at: Placement<'_>,
        pushed: &translux_proto::csr::CsrView<'_, [f32; 3]>,
    ) -> Result<(), usize> {
        let n = f.n;
        let Some(nodes) = at.nodes.filter(|_| !self.recv.is_empty()) else {
            return Ok(());
        };
        // The object's node rows (as rows of `f`) holding each of its patches.
        let mut holders: Vec<Vec<usize>> = vec![Vec::new(); n];
        for (x, &m) in self.recv.iter().enumerate() {
            let [a, b] = nodes.range[m as usize];
            for &p in &nodes.perm[a as usize..b as usize] {
                let j = (p as usize).wrapping_sub(at.start);
                let h = holders.get_mut(j).ok_or(at.n + m as usize)?;
                h.push(n + x);
            }
        }
        let mut push_ptr = vec![0u32];
        let mut items: Vec<u32> = Vec::new();
        let row_ptr = pushed.row_ptr();
        for (j, held) in holders.iter().enumerate() {
            // (column, value) of the row and of the node rows holding it, by column.
            let mut all: Vec<(u32, u32)> = Vec::new();
            for r in std::iter::once(j).chain(held.iter().copied()) {
                all.extend(self.row_values(f, r, at));
            }
            all.sort_unstable();
            let (cols, _) = pushed.row(at.start + j);
            let mut at_col = 0usize;
            for group in all.chunk_by(|a, b| a.0 == b.0) {
                if cols.get(at_col) != Some(&group[0].0) {
                    return Err(at.start + j);
                }
                items.extend(group.iter().map(|g| g.1));
                push_ptr.push(items.len() as u32);
                at_col += 1;
            }
            if at_col != cols.len() {
                return Err(at.start + j);
            }
        }
        let first = row_ptr[at.start];
        f.pushed = (row_ptr[at.start + n] - first) as usize;
        f.runs = Vec::new();
        push_run(&mut f.runs, first, 0, f.pushed as u32);
        f.push_ptr = push_ptr;
        f.push_items = items;
        Ok(())
    }

    /// Row r of `f` (a patch's, or a node row's) as (S's column, its value's index).
    fn row_values<'f>(
        &'f self,
        f: &'f FlatTerms,
        r: usize,
        at: Placement<'f>,
    ) -> impl Iterator<Item = (u32, u32)> + 'f {
        let row = f.rows[r];
        let entries = (row.entries[0]..row.entries[1]).map(move |e| {
            (
                at.start as u32 + f.entries[e as usize].src,
                row.value + e - row.entries[0],
            )
        });
        let links = (row.links[0]..row.links[1]).map(move |l| {
            let link = &f.links[l as usize];
            let k = link.node_index() + self.links.nodes.start;
            ((at.n + k) as u32, link.value)
        });
        entries.chain(links)
    }

    /// Row j's place (a patch's for j < n, node row j − n's after): the links it reads
    /// and its index among them, its entries, its row of S and its receiver's area.
    fn row_place(
        &self,
        j: usize,
        area: &[f32],
        at: Placement<'_>,
    ) -> (&super::Links, usize, std::ops::Range<u32>, usize, f32) {
        let n = self.row_ptr.len() - 1;
        match at.nodes {
            Some(nodes) if j >= n => {
                let m = self.recv[j - n] as usize;
                (&self.pairs, j - n, 0..0, at.n + m, nodes.area[m])
            }
            _ => (
                &self.links,
                j,
                self.row_ptr[j]..self.row_ptr[j + 1],
                at.start + j,
                area[j],
            ),
        }
    }

    /// The entries (with their end sentinel) and terms of `f`.
    fn flat_entries(&self, f: &mut FlatTerms) {
        f.entries = (0..self.src.len())
            .map(|e| FlatEntry {
                src: self.src[e],
                dist: self.dist[e],
                hi_max: self.hi_max[e],
                terms: self.term_ptr[e] | if self.opposite[e] { OPPOSITE } else { 0 },
            })
            .collect();
        f.entries.push(FlatEntry {
            src: u32::MAX,
            dist: 0.0,
            hi_max: 0.0,
            terms: self.term_ptr[self.src.len()],
        });
        f.terms = self
            .packed
            .iter()
            .zip(&self.bounds)
            .map(|(&[root, weight], &[lo, hi])| [root, weight, lo, hi])
            .collect();
    }

    /// Link `l` of `set` as a record, its value at `value`.
    fn flat_link(&self, set: &super::Links, l: usize, at: Placement<'_>, value: u32) -> FlatLink {
        let k = set.col[l] as usize - at.n;
        let two = set.two.get(l).copied();
        let flags =
            if set.opposite[l] { OPPOSITE } else { 0 } | if two.is_some() { TWO } else { 0 };
        FlatLink {
            root: set.root[l],
            two: two.unwrap_or([0.0; 2]),
            area: at.nodes.map_or(0.0, |nodes| nodes.area[k]),
            node: (k - self.links.nodes.start) as u32 | flags,
            value,
            _pad: [0; 2],
        }
    }

    /// The column and node gathers of `f` (its rows and links made).
    fn flat_gathers(&self, f: &mut FlatTerms) {
        let n = f.n;
        f.column_ptr = self.by_src_ptr.clone();
        f.column_items = self
            .by_src
            .iter()
            .map(|&[j, e]| {
                let row = &f.rows[j as usize];
                [row.value + (e - row.entries[0]), row.area.to_bits()]
            })
            .collect();
        let mut count = vec![0u32; f.nodes + 1];
        for l in &f.links {
            count[l.node_index() + 1] += 1;
        }
        for k in 0..f.nodes {
            count[k + 1] += count[k];
        }
        let mut next = count[..f.nodes].to_vec();
        f.node_items = vec![[0u32; 2]; f.links.len()];
        for row in &f.rows {
            for l in row.links[0]..row.links[1] {
                let k = f.links[l as usize].node_index();
                f.node_items[next[k] as usize] = [l, row.area.to_bits()];
                next[k] += 1;
            }
        }
        f.node_ptr = count;
        debug_assert_eq!(f.column_ptr.len(), n + 1);
    }
}

/// Appends a run of `len` values (S's from `s_value`, the object's from `local`), joined to
/// the last run where they continue it.
fn push_run(runs: &mut Vec<ValueRun>, s_value: u64, local: u32, len: u32) {
    if len == 0 {
        return;
    }
    if let Some(last) = runs.last_mut()
        && last.s_value + last.len as u64 == s_value
        && last.local + last.len == local
    {
        last.len += len;
        return;
    }
    runs.push(ValueRun {
        s_value,
        local,
        len,
    });
}
