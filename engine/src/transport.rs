//! The form-factor operator the solvers apply: y = F x.
//!
//! In: a bundle's F arrays — dense (one entry per visible patch pair) or hierarchical (C over
//! patches and cluster nodes, with the cluster tree, see
//! [`translux_proto::bundle::Manifest::hierarchy`]). Out: products y = F x for any number of
//! RGB systems, a Gauss-Seidel sweep's source values, F's row sums, and F written out
//! densely where a dense factorisation needs it (the transfer matrix T).
//!
//! Hierarchical F̃ = C·P. P pulls the area-weighted mean of x over every cluster node. Each
//! node covers a contiguous range of the tree's patch order, so one prefix sum of A x in that
//! order gives every node's mean as a difference of two prefix values — O(N + M) per
//! product, however deep the tree. The pulled vector x̄ = [x; P x] has N + M rows and C is an
//! ordinary CSR matrix over it, so the CSR products serve both kinds unchanged.
//!
//! A two-sided F̃ = Q·C·P (`translux-precompute --links two-sided`) also links cluster nodes
//! as receivers: C then has N + M rows, row N + k holding what node k's patches receive
//! alike, and Q pushes each node row down to every patch of the node — a difference array
//! over the same tree order, O(N + M) as the pull is.
//!
//! A hierarchical S (`translux-precompute --subsurface hierarchical`) is built the same way
//! over the same tree: [`LinkedScatter`] pulls the irradiance and applies S̃ = C_S·P, C_S
//! holding near pairs in its first N columns and links to whole nodes after them
//! ([`subsurface_operator`] picks it for a bundle's S).

use rayon::prelude::*;
use translux_proto::bundle::{Bundle, TreeView};
use translux_proto::csr::{Csr, CsrError, CsrView};

use crate::linalg::{Rgb, Scatter, SparseScatter};

/// F as the solvers see it: a dense CSR matrix, or C with the tree P pulls over.
#[derive(Debug, Clone, Copy)]
pub struct Transport<'a> {
    f: CsrView<'a>,
    tree: Option<Tree<'a>>,
    /// The bundle F came from ([`Transport::of`]): its products read F's columns in 16
    /// bits ([`Bundle::form_factor_cols`], made by the first product, so a transport that
    /// never multiplies on the CPU never makes them).
    bundle: Option<&'a Bundle>,
}

/// The cluster tree with the patch areas its means are weighted by.
#[derive(Debug, Clone, Copy)]
struct Tree<'a> {
    view: TreeView<'a>,
    area: &'a [f32],
}

/// Scratch space of [`Transport::apply_multi`]: the pulled vector and the prefix sums (kept
/// between products so a solve allocates them once).
#[derive(Debug, Default)]
pub struct Pulled {
    /// x̄ = [x; P x], `(N + M) × ch`.
    pub values: Vec<f32>,
    prefix: Vec<f64>,
    /// C x̄ over every row of a two-sided C, `(N + M) × ch`, before the push.
    rows: Vec<f32>,
}

impl<'a> Tree<'a> {
    /// Adds node rows' values `node_y` (`M × ch`) to every patch of each node (`y`: `N ×
    /// ch`): a difference array over the tree's order, summed in f64 so that a patch deep
    /// in the order does not carry the rounding of every node closed before it.
    fn push(&self, node_y: &[f32], y: &mut [f32], ch: usize) {
        let perm = self.view.perm;
        let mut diff = vec![0.0f64; (perm.len() + 1) * ch];
        for (v, r) in node_y.chunks_exact(ch).zip(self.view.range) {
            if v.iter().all(|&x| x == 0.0) {
                continue;
            }
            let (a, b) = (r[0] as usize * ch, r[1] as usize * ch);
            for c in 0..ch {
                diff[a + c] += v[c] as f64;
                diff[b + c] -= v[c] as f64;
            }
        }
        let mut run = vec![0.0f64; ch];
        for (q, &p) in perm.iter().enumerate() {
            let yp = &mut y[p as usize * ch..(p as usize + 1) * ch];
            for c in 0..ch {
                run[c] += diff[q * ch + c];
                yp[c] += run[c] as f32;
            }
        }
    }

    /// x̄ = [x; P x] into `out.values` (`x` is `N × ch`).
    fn pull(&self, x: &[f32], ch: usize, out: &mut Pulled) {
        let n = self.view.perm.len();
        let m = self.view.range.len();
        out.values.resize((n + m) * ch, 0.0);
        out.values[..n * ch].copy_from_slice(&x[..n * ch]);
        // prefix[k] = Σ_{q<k} (A, A x) of the patches in tree order; one extra column for
        // the area itself, so each node's mean is a ratio of two differences.
        let w = ch + 1;
        out.prefix.resize((n + 1) * w, 0.0);
        out.prefix[..w].fill(0.0);
        for (k, &p) in self.view.perm.iter().enumerate() {
            let (p, a) = (p as usize, self.area[p as usize] as f64);
            let (head, tail) = out.prefix.split_at_mut((k + 1) * w);
            let prev = &head[k * w..];
            let next = &mut tail[..w];
            next[0] = prev[0] + a;
            for c in 0..ch {
                next[c + 1] = prev[c + 1] + a * x[p * ch + c] as f64;
            }
        }
        let prefix = &out.prefix;
        out.values[n * ch..]
            .par_chunks_mut(ch)
            .with_min_len(256)
            .zip(self.view.range.par_iter())
            .for_each(|(v, r)| {
                let (a, b) = (&prefix[r[0] as usize * w..], &prefix[r[1] as usize * w..]);
                let area = b[0] - a[0];
                for c in 0..ch {
                    v[c] = ((b[c + 1] - a[c + 1]) / area) as f32;
                }
            });
    }
}

impl<'a> Transport<'a> {
    /// A dense F (`N × N`).
    pub fn dense(f: CsrView<'a>) -> Self {
        assert_eq!(f.n_rows(), f.n_cols(), "a dense F is square");
        Self {
            f,
            tree: None,
            bundle: None,
        }
    }

    /// A hierarchical F̃ = C·P: `c` is `N × (N + M)` over the patches then the nodes of
    /// `tree`, whose means are weighted by `area` (`[N]`) — or `(N + M) × (N + M)` for a
    /// two-sided F̃ = Q·C·P, whose node rows are pushed to their patches. The bundle loader
    /// has checked that the tree's permutation and ranges are valid; the shapes are checked
    /// here.
    pub fn hierarchical(c: CsrView<'a>, tree: TreeView<'a>, area: &'a [f32]) -> Self {
        let n = tree.perm.len();
        assert!(
            c.n_rows() == n || c.n_rows() == n + tree.range.len(),
            "C's rows: the patches, or the patches then the nodes"
        );
        assert_eq!(area.len(), n, "an area per patch");
        assert_eq!(
            c.n_cols(),
            n + tree.range.len(),
            "C's columns: patches, then nodes"
        );
        Self {
            f: c,
            tree: Some(Tree { view: tree, area }),
            bundle: None,
        }
    }

    /// The F a bundle holds, dense or hierarchical. Its products read F's columns in 16
    /// bits ([`Bundle::form_factor_cols`]).
    pub fn of(b: &'a Bundle) -> Self {
        let t = match b.tree() {
            Some(t) => Self::hierarchical(b.form_factors(), t, b.patch_areas()),
            None => Self::dense(b.form_factors()),
        };
        Self {
            bundle: Some(b),
            ..t
        }
    }

    /// Patches N (rows of F).
    pub fn n(&self) -> usize {
        self.tree.map_or(self.f.n_rows(), |t| t.view.perm.len())
    }

    /// Whether cluster nodes receive too (a two-sided F̃ = Q·C·P: C has N + M rows).
    pub fn has_node_rows(&self) -> bool {
        self.f.n_rows() > self.n()
    }

    /// Cluster nodes M (0 for a dense F).
    pub fn nodes(&self) -> usize {
        self.f.n_cols() - self.n()
    }

    /// Whether F is hierarchical.
    pub fn is_hierarchical(&self) -> bool {
        self.tree.is_some()
    }

    /// The stored matrix: F itself, or C (whose columns past N are nodes, and whose rows
    /// past N, when [`Transport::has_node_rows`], are nodes' rows: see
    /// [`Transport::holders`] for the rows a patch receives through).
    pub fn matrix(&self) -> &CsrView<'a> {
        &self.f
    }

    /// Stored entries.
    pub fn nnz(&self) -> usize {
        self.f.nnz()
    }

    /// Fills `out.values` with x̄ = [x; P x] for `ch` channels per patch (`x` is `N × ch`).
    pub fn pull(&self, x: &[f32], ch: usize, out: &mut Pulled) {
        match &self.tree {
            Some(t) => t.pull(x, ch, out),
            None => {
                let n = self.n();
                out.values.resize(n * ch, 0.0);
                out.values.copy_from_slice(&x[..n * ch]);
            }
        }
    }

    /// y = F x for `ch` channels per patch: one pass over the stored matrix serves every
    /// channel (and a two-sided C's node rows are pushed after). `scratch` is reused
    /// between calls.
    pub fn apply_multi(&self, x: &[f32], y: &mut [f32], ch: usize, scratch: &mut Pulled) {
        if self.tree.is_some() {
            self.pull(x, ch, scratch);
        }
        let x = if self.tree.is_none() {
            x
        } else {
            &scratch.values
        };
        let Some(tree) = self.tree.filter(|_| self.has_node_rows()) else {
            self.spmv(x, y, ch);
            return;
        };
        let n = self.n();
        let rows = &mut scratch.rows;
        rows.resize(self.f.n_rows() * ch, 0.0);
        self.spmv(x, rows, ch);
        y[..n * ch].copy_from_slice(&rows[..n * ch]);
        tree.push(&rows[n * ch..], y, ch);
    }

    /// Every stored row's product over the pulled vector `x` (y has as many rows as it
    /// holds).
    fn spmv(&self, x: &[f32], y: &mut [f32], ch: usize) {
        match self.bundle {
            Some(b) => crate::linalg::spmv_multi_narrow(&self.f, b.form_factor_cols(), x, y, ch),
            None => crate::linalg::spmv_multi(&self.f, x, y, ch),
        }
    }

    /// The node rows of a two-sided C over the pulled vector `xbar` (`(N + M) × ch`, from
    /// [`Transport::pull`]), pushed to their patches: what each patch receives through the
    /// nodes that hold it (`N × ch`). `None` when no node receives.
    pub fn node_rows_pushed(&self, xbar: &[f32], ch: usize) -> Option<Vec<f32>> {
        let tree = self.tree.filter(|_| self.has_node_rows())?;
        let (n, m) = (self.n(), self.nodes());
        let mut node_y = vec![0.0f32; m * ch];
        node_y
            .par_chunks_mut(ch)
            .with_min_len(64)
            .enumerate()
            .for_each(|(k, yk)| {
                let (cols, vals) = self.f.row(n + k);
                for (&j, &v) in cols.iter().zip(vals) {
                    let xj = &xbar[j as usize * ch..(j as usize + 1) * ch];
                    for (a, &b) in yk.iter_mut().zip(xj) {
                        *a += v * b;
                    }
                }
            });
        let mut y = vec![0.0f32; n * ch];
        tree.push(&node_y, &mut y, ch);
        Some(y)
    }

    /// For each patch p with `wanted(p)`, the nodes whose (non-empty) rows it receives
    /// through, root first; empty lists without node rows. O(N × depth) at worst: for
    /// consumers that need whole patch rows ([`Transport::patch_row`]).
    pub fn holders(&self, wanted: impl Fn(usize) -> bool) -> Vec<Vec<u32>> {
        let n = self.n();
        let mut out = vec![Vec::new(); n];
        let Some(tree) = self.tree.filter(|_| self.has_node_rows()) else {
            return out;
        };
        for (k, r) in tree.view.range.iter().enumerate() {
            if self.f.row(n + k).0.is_empty() {
                continue;
            }
            for &p in &tree.view.perm[r[0] as usize..r[1] as usize] {
                if wanted(p as usize) {
                    out[p as usize].push(k as u32);
                }
            }
        }
        out
    }

    /// Patch i's whole row of C: its own entries and those of the node rows it receives
    /// through (`holders`: [`Transport::holders`]'s list for i), one entry per column,
    /// columns ascending.
    pub fn patch_row(&self, i: usize, holders: &[u32]) -> (Vec<u32>, Vec<f32>) {
        let (cols, vals) = self.f.row(i);
        if holders.is_empty() {
            return (cols.to_vec(), vals.to_vec());
        }
        let n = self.n();
        let mut row: Vec<(u32, f32)> = cols.iter().copied().zip(vals.iter().copied()).collect();
        for &k in holders {
            let (c, v) = self.f.row(n + k as usize);
            row.extend(c.iter().copied().zip(v.iter().copied()));
        }
        row.sort_by_key(|e| e.0);
        let mut out: (Vec<u32>, Vec<f32>) = (Vec::with_capacity(row.len()), Vec::new());
        for (c, v) in row {
            match out.0.last() {
                Some(&lc) if lc == c => *out.1.last_mut().expect("paired") += v,
                _ => {
                    out.0.push(c);
                    out.1.push(v);
                }
            }
        }
        out
    }

    /// The push as a matrix, `N × (N + M)`: the identity over the patch rows, then a 1 in
    /// column N + k of every patch of node k — so y = Q' (C x̄) is a CSR product (the GPU
    /// backend's form of the push, tested against [`Transport::apply_multi`]). `None`
    /// without node rows. About N × (tree depth + 1) entries.
    pub fn push_matrix(&self) -> Option<Csr> {
        let tree = self.tree.filter(|_| self.has_node_rows())?;
        let n = self.n();
        let mut by_patch: Vec<Vec<u32>> = vec![Vec::new(); n];
        for (k, r) in tree.view.range.iter().enumerate() {
            for &p in &tree.view.perm[r[0] as usize..r[1] as usize] {
                by_patch[p as usize].push((n + k) as u32);
            }
        }
        let rows: Vec<Vec<(u32, f32)>> = by_patch
            .into_iter()
            .enumerate()
            .map(|(p, mut nodes)| {
                nodes.sort_unstable();
                std::iter::once((p as u32, 1.0))
                    .chain(nodes.into_iter().map(|c| (c, 1.0)))
                    .collect()
            })
            .collect();
        Csr::from_rows(self.f.n_rows(), &rows).ok()
    }

    /// y = F x for one RGB vector.
    pub fn apply_rgb(&self, x: &[Rgb], y: &mut [Rgb]) {
        self.apply_multi(
            bytemuck::cast_slice(x),
            bytemuck::cast_slice_mut(y),
            3,
            &mut Pulled::default(),
        );
    }

    /// The pull as a matrix, `(N + M) × N`: the identity over the patches, then row N + k
    /// holding A_p / A_k for the patches p of node k — so x̄ = P' x is a CSR product (the GPU
    /// backend's form of [`Transport::pull`], which it is tested against). `None` for a
    /// dense F. About N × (tree depth + 1) entries.
    pub fn pull_matrix(&self) -> Option<Csr> {
        let t = self.tree.as_ref()?;
        let n = self.n();
        let mut out = Csr {
            n_rows: n + self.nodes(),
            n_cols: n,
            row_ptr: Vec::with_capacity(n + self.nodes() + 1),
            col: Vec::with_capacity(n),
            val: Vec::with_capacity(n),
        };
        out.row_ptr.push(0);
        for p in 0..n {
            out.col.push(p as u32);
            out.val.push(1.0);
            out.row_ptr.push(out.col.len() as u64);
        }
        let mut patches = Vec::new();
        for r in t.view.range {
            patches.clear();
            patches.extend_from_slice(&t.view.perm[r[0] as usize..r[1] as usize]);
            patches.sort_unstable();
            let area: f64 = patches.iter().map(|&p| t.area[p as usize] as f64).sum();
            for &p in &patches {
                out.col.push(p);
                out.val.push((t.area[p as usize] as f64 / area) as f32);
            }
            out.row_ptr.push(out.col.len() as u64);
        }
        Some(out)
    }

    /// y = A x for the stored matrix alone (no pull; any shape): tests.
    #[cfg(test)]
    fn apply_rgb_unchecked(&self, x: &[Rgb], y: &mut [Rgb]) {
        crate::linalg::spmv_rgb(&self.f, x, y);
    }

    /// Σ_j F_ij per patch (P keeps constants, so these are C's row sums, a two-sided C's
    /// node rows added to their patches).
    pub fn row_sums(&self) -> Vec<f64> {
        let sum = |i: usize| self.f.row(i).1.iter().map(|&v| v as f64).sum::<f64>();
        let mut sums: Vec<f64> = (0..self.n()).into_par_iter().map(sum).collect();
        if let Some(tree) = self.tree.filter(|_| self.has_node_rows()) {
            let n = self.n();
            let node: Vec<f32> = (n..self.f.n_rows()).map(|k| sum(k) as f32).collect();
            let mut pushed = vec![0.0f32; n];
            tree.push(&node, &mut pushed, 1);
            for (s, p) in sums.iter_mut().zip(pushed) {
                *s += p as f64;
            }
        }
        sums
    }

    /// F as an `N × N` CSR matrix: C·P multiplied out (each node entry spread over the
    /// node's patches by area). For a dense F, a copy. Costs O(N²) memory at worst: only
    /// for what a dense factorisation needs anyway (the transfer matrix T).
    pub fn expand(&self) -> Csr {
        let n = self.n();
        let holders = self.holders(|_| true);
        let rows: Vec<(Vec<u32>, Vec<f32>)> = (0..n)
            .into_par_iter()
            .map_init(
                || vec![0.0f64; n],
                |acc, i| {
                    let (cols, vals) = self.patch_row(i, &holders[i]);
                    let (cols, vals) = (cols.as_slice(), vals.as_slice());
                    for (&j, &v) in cols.iter().zip(vals) {
                        let j = j as usize;
                        match &self.tree {
                            Some(t) if j >= n => {
                                let r = t.view.range[j - n];
                                let patches = &t.view.perm[r[0] as usize..r[1] as usize];
                                let area: f64 =
                                    patches.iter().map(|&p| t.area[p as usize] as f64).sum();
                                for &p in patches {
                                    acc[p as usize] += v as f64 * t.area[p as usize] as f64 / area;
                                }
                            }
                            _ => acc[j] += v as f64,
                        }
                    }
                    let (mut c, mut w) = (Vec::new(), Vec::new());
                    for (j, a) in acc.iter_mut().enumerate() {
                        if *a != 0.0 {
                            c.push(j as u32);
                            w.push(*a as f32);
                            *a = 0.0;
                        }
                    }
                    (c, w)
                },
            )
            .collect();
        let mut out = Csr {
            n_rows: n,
            n_cols: n,
            row_ptr: Vec::with_capacity(n + 1),
            col: Vec::new(),
            val: Vec::new(),
        };
        out.row_ptr.push(0);
        for (c, w) in rows {
            out.col.extend(c);
            out.val.extend(w);
            out.row_ptr.push(out.col.len() as u64);
        }
        out
    }
}

/// A hierarchical S̃ = C_S·P as the solvers apply it: C_S is `N × (N + M)` (RGB entries;
/// columns past N gather a cluster node's area-weighted mean whole), P the same pull as a
/// hierarchical F's over the bundle's cluster tree. Built by [`subsurface_operator`].
///
/// C_S may also hold M node rows after its N patch rows (`(N + M) × (N + M)`): row N + m
/// is what node m's patches gather alike (node-to-node links, docs/hierarchy.md,
/// *Receiver-side clustering*), so S̃ = Q·C_S·P with Q the push, the transpose of the
/// pull's membership: patch j receives its own row plus the rows of every node holding
/// it. Node m covers a contiguous range of the tree's order, so one difference array over
/// that order pushes every node row at once, O(N + M) per product as the pull is.
///
/// With column factors ([`LinkedScatter::with_columns`]), S̃ = C_S·D·P: the pulled vector
/// is scaled column by column before the product (the energy bound's factors of an S
/// written in place, `crate::smatrix::ColumnScale`).
#[derive(Debug, Clone, Copy)]
pub struct LinkedScatter<'a> {
    s: CsrView<'a, Rgb>,
    tree: Tree<'a>,
    columns: Option<&'a [Rgb]>,
}

impl<'a> LinkedScatter<'a> {
    /// S̃ with the tree its node columns (and node rows, if any) refer to (`area`: `[N]`).
    pub fn new(s: CsrView<'a, Rgb>, tree: TreeView<'a>, area: &'a [f32]) -> Self {
        let (n, m) = (tree.perm.len(), tree.range.len());
        assert_eq!(area.len(), n, "an area per patch");
        assert_eq!(s.n_cols(), n + m, "S's columns: patches, then nodes");
        assert!(
            s.n_rows() == n || s.n_rows() == n + m,
            "S's rows: the patches, or the patches then the nodes"
        );
        Self {
            s,
            tree: Tree { view: tree, area },
            columns: None,
        }
    }

    /// S̃ whose columns (patches, then nodes: `[N + M]`) are further scaled by `columns`.
    pub fn with_columns(self, columns: &'a [Rgb]) -> Self {
        assert_eq!(columns.len(), self.s.n_cols(), "a factor per column of S");
        Self {
            columns: Some(columns),
            ..self
        }
    }

    /// Whether S has node rows (pushed down to the patches).
    pub fn has_node_rows(&self) -> bool {
        self.s.n_rows() > self.tree.view.perm.len()
    }
}

impl Scatter for LinkedScatter<'_> {
    fn apply(&self, h: &[Rgb], y: &mut [Rgb]) {
        self.apply_multi(bytemuck::cast_slice(h), bytemuck::cast_slice_mut(y), 3);
    }
    fn apply_multi(&self, h: &[f32], y: &mut [f32], ch: usize) {
        let mut pulled = Pulled::default();
        self.tree.pull(h, ch, &mut pulled);
        if let Some(d) = self.columns {
            scale_columns(&mut pulled.values, d, ch);
        }
        // The patch rows (a product fills as many rows as `y` holds), and the node rows
        // pushed to their patches after: one product, the pulled values laid out once.
        let n = self.tree.view.perm.len();
        let m = if self.has_node_rows() {
            self.tree.view.range.len()
        } else {
            0
        };
        let mut node_y = vec![0.0f32; m * ch];
        let patch_rows = 0..y.len() / ch.max(1);
        crate::linalg::scatter_rows(
            &self.s,
            &pulled.values,
            ch,
            &mut [(patch_rows, &mut *y), (n..n + m, &mut node_y)],
        );
        if m > 0 {
            self.tree.push(&node_y, y, ch);
        }
    }
    fn diagonal(&self) -> Option<&[Rgb]> {
        None
    }
}

/// A hierarchical S with node rows ([`LinkedScatter`]) written out as `N × (N + M)`: each
/// patch's row gets the rows of the nodes holding it, entries of one column summed,
/// columns ascending. What a consumer that multiplies patch rows alone needs (the GPU
/// backend's product of an S built on the CPU); an S without node rows comes back as it is.
/// Fails only where a summed value is not finite.
pub fn push_node_rows(s: CsrView<'_, Rgb>, tree: TreeView<'_>) -> Result<Csr<Rgb>, CsrError> {
    let n = tree.perm.len();
    // The nodes whose rows hold something, by patch: a patch at tree position q is held by
    // every node whose range contains q.
    let mut holders: Vec<Vec<u32>> = vec![Vec::new(); n];
    for (k, r) in tree.range.iter().enumerate().filter(|_| s.n_rows() > n) {
        if s.row(n + k).0.is_empty() {
            continue;
        }
        for &p in &tree.perm[r[0] as usize..r[1] as usize] {
            holders[p as usize].push(k as u32);
        }
    }
    let rows: Vec<Vec<(u32, Rgb)>> = (0..n)
        .into_par_iter()
        .map(|j| {
            let (cols, vals) = s.row(j);
            let mut row: Vec<(u32, Rgb)> = cols.iter().copied().zip(vals.iter().copied()).collect();
            for &k in &holders[j] {
                let (c, v) = s.row(n + k as usize);
                row.extend(c.iter().copied().zip(v.iter().copied()));
            }
            row.sort_by_key(|e| e.0);
            let mut merged: Vec<(u32, Rgb)> = Vec::with_capacity(row.len());
            for (c, v) in row {
                match merged.last_mut() {
                    Some((lc, lv)) if *lc == c => {
                        for ch in 0..3 {
                            lv[ch] += v[ch];
                        }
                    }
                    _ => merged.push((c, v)),
                }
            }
            merged
        })
        .collect();
    Csr::from_rows(s.n_cols(), &rows)
}

/// The scattering operator of a bundle's S (its own, or one rebuilt for overrides, `s`):
/// a sparse S, or [`LinkedScatter`] when S has node columns (a hierarchical S).
pub fn subsurface_operator<'a>(b: &'a Bundle, s: CsrView<'a, Rgb>) -> Box<dyn Scatter + 'a> {
    subsurface_operator_scaled(b, s, None)
}

/// [`subsurface_operator`] for S = `s` × diag(`columns`), one factor per column of `s`
/// (`crate::smatrix::OverrideMaterials::s_parts`): each product scales its vector, S's
/// values stay as they are.
pub fn subsurface_operator_scaled<'a>(
    b: &'a Bundle,
    s: CsrView<'a, Rgb>,
    columns: Option<&'a [Rgb]>,
) -> Box<dyn Scatter + 'a> {
    match (b.tree(), columns) {
        (Some(t), d) if s.n_cols() > b.patch_areas().len() => {
            let op = LinkedScatter::new(s, t, b.patch_areas());
            Box::new(match d {
                Some(d) => op.with_columns(d),
                None => op,
            })
        }
        (_, Some(d)) => Box::new(ScaledScatter {
            s: SparseScatter(s),
            columns: d,
        }),
        _ => Box::new(SparseScatter(s)),
    }
}

/// Scales `x` (`[column][ch]`) column by column: channel c by factor component c % 3.
fn scale_columns(x: &mut [f32], d: &[Rgb], ch: usize) {
    x.par_chunks_mut(ch)
        .with_min_len(1024)
        .zip(d.par_iter())
        .for_each(|(x, f)| {
            if *f != [1.0; 3] {
                for (c, v) in x.iter_mut().enumerate() {
                    *v *= f[c % 3];
                }
            }
        });
}

/// A sparse S whose columns are further scaled (S·D, D diagonal): D applied to the vector
/// first.
struct ScaledScatter<'a> {
    s: SparseScatter<'a>,
    columns: &'a [Rgb],
}

impl Scatter for ScaledScatter<'_> {
    fn apply(&self, h: &[Rgb], y: &mut [Rgb]) {
        self.apply_multi(bytemuck::cast_slice(h), bytemuck::cast_slice_mut(y), 3);
    }
    fn apply_multi(&self, h: &[f32], y: &mut [f32], ch: usize) {
        let mut x = h.to_vec();
        scale_columns(&mut x, self.columns, ch);
        self.s.apply_multi(&x, y, ch);
    }
    fn diagonal(&self) -> Option<&[Rgb]> {
        None
    }
}

/// Each cluster node's area Σ A_p over its patches (`[M]`).
pub fn node_areas(tree: TreeView<'_>, area: &[f32]) -> Vec<f32> {
    let mut prefix = Vec::with_capacity(tree.perm.len() + 1);
    prefix.push(0.0f64);
    let mut acc = 0.0f64;
    for &p in tree.perm {
        acc += area[p as usize] as f64;
        prefix.push(acc);
    }
    tree.range
        .iter()
        .map(|r| (prefix[r[1] as usize] - prefix[r[0] as usize]) as f32)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Four patches, two nodes: {0, 2} and {0, 1, 2, 3}, perm [2, 0, 3, 1].
    fn fixture() -> (Vec<u32>, Vec<[u32; 2]>, Vec<f32>, Csr) {
        let perm = vec![2, 0, 3, 1];
        let range = vec![[0, 2], [0, 4]];
        let area = vec![1.0, 2.0, 3.0, 4.0];
        // Row 0: 0.5·node0; row 1: 0.25·patch 0 + 0.5·node1; rows 2, 3: 0.1·node1.
        let c = Csr {
            n_rows: 4,
            n_cols: 6,
            row_ptr: vec![0, 1, 3, 4, 5],
            col: vec![4, 0, 5, 5, 5],
            val: vec![0.5, 0.25, 0.5, 0.1, 0.1],
        };
        (perm, range, area, c)
    }

    #[test]
    fn the_pull_is_the_area_weighted_mean_and_expand_agrees_with_apply() {
        let (perm, range, area, c) = fixture();
        let view = c.view().unwrap();
        let t = Transport::hierarchical(
            view,
            TreeView {
                perm: &perm,
                range: &range,
            },
            &area,
        );
        assert_eq!((t.n(), t.nodes()), (4, 2));
        let x: Vec<Rgb> = vec![
            [1.0, 0.0, 2.0],
            [2.0, 1.0, 0.0],
            [3.0, 0.0, 1.0],
            [4.0, 2.0, 0.0],
        ];
        let mut pulled = Pulled::default();
        t.pull(bytemuck::cast_slice(&x), 3, &mut pulled);
        // Node 0 = patches {2, 0}: (3·3 + 1·1)/4 = 2.5 in red.
        assert!((pulled.values[4 * 3] - 2.5).abs() < 1e-6);
        // Node 1 = all: (1 + 4 + 9 + 16)/10 = 3 in red, (2 + 8)/10 = 1 in green.
        assert!((pulled.values[5 * 3] - 3.0).abs() < 1e-6);
        assert!((pulled.values[5 * 3 + 1] - 1.0).abs() < 1e-6);
        let mut y = vec![[0.0f32; 3]; 4];
        t.apply_rgb(&x, &mut y);
        let dense = t.expand();
        let d = Transport::dense(dense.view().unwrap());
        let mut yd = vec![[0.0f32; 3]; 4];
        d.apply_rgb(&x, &mut yd);
        for (a, b) in y.iter().zip(&yd) {
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() < 1e-6, "{y:?} vs {yd:?}");
            }
        }
        // A constant is transported by the row sums.
        let sums = t.row_sums();
        t.apply_rgb(&[[1.0; 3]; 4], &mut y);
        for (s, yi) in sums.iter().zip(&y) {
            assert!((*s as f32 - yi[0]).abs() < 1e-6);
        }
        assert_eq!(dense.row_ptr, vec![0, 2, 6, 10, 14]);
        // The pull as a matrix gives the same x̄.
        let p = t.pull_matrix().unwrap();
        let pv = p.view().unwrap();
        let mut xbar = vec![[0.0f32; 3]; 6];
        Transport {
            f: pv,
            tree: None,
            bundle: None,
        }
        .apply_rgb_unchecked(&x, &mut xbar);
        t.pull(bytemuck::cast_slice(&x), 3, &mut pulled);
        for (a, b) in bytemuck::cast_slice::<_, f32>(&xbar)
            .iter()
            .zip(&pulled.values)
        {
            assert!((a - b).abs() < 1e-6);
        }
    }

    /// The fixture's C with two node rows after its patch rows (a two-sided F̃ = Q·C·P):
    /// node 0 ({2, 0}) receives 0.2·patch 1 + 0.3·patch 3, node 1 (all) 0.05·node 0.
    fn two_sided() -> Csr {
        let (_, _, _, mut c) = fixture();
        c.n_rows = 6;
        c.col.extend([1, 3, 4]);
        c.val.extend([0.2, 0.3, 0.05]);
        c.row_ptr.extend([7, 8]);
        c
    }

    #[test]
    fn node_rows_of_f_are_pushed_to_every_patch_of_their_node() {
        let (perm, range, area, _) = fixture();
        let c = two_sided();
        let tree = TreeView {
            perm: &perm,
            range: &range,
        };
        let t = Transport::hierarchical(c.view().unwrap(), tree, &area);
        assert!(t.has_node_rows());
        assert_eq!((t.n(), t.nodes()), (4, 2));
        let x: Vec<Rgb> = vec![
            [1.0, 0.0, 2.0],
            [2.0, 1.0, 0.0],
            [3.0, 0.0, 1.0],
            [4.0, 2.0, 0.0],
        ];
        let mut y = vec![[0.0f32; 3]; 4];
        t.apply_rgb(&x, &mut y);
        // By hand, red: node 0's mean 2.5, node 1's 3; node rows 0.2·2 + 0.3·4 = 1.6 and
        // 0.05·2.5 = 0.125. Patch 0 (in both nodes): 0.5·2.5 + 1.6 + 0.125; patch 1 (node 1
        // only): 0.25·1 + 0.5·3 + 0.125; patch 2 (both): 0.1·3 + 1.725; patch 3: 0.3 + 0.125.
        let want = [1.25 + 1.725, 0.25 + 1.5 + 0.125, 0.3 + 1.725, 0.3 + 0.125];
        for (i, w) in want.iter().enumerate() {
            assert!((y[i][0] - w).abs() < 1e-6, "patch {i}: {} vs {w}", y[i][0]);
        }
        // Written out, as rows, as row sums and as the device's push: the same operator.
        let dense = t.expand();
        let mut yd = vec![[0.0f32; 3]; 4];
        Transport::dense(dense.view().unwrap()).apply_rgb(&x, &mut yd);
        let holders = t.holders(|_| true);
        assert_eq!(holders, vec![vec![0, 1], vec![1], vec![0, 1], vec![1]]);
        let sums = t.row_sums();
        let mut ones = vec![[0.0f32; 3]; 4];
        t.apply_rgb(&[[1.0; 3]; 4], &mut ones);
        let q = t.push_matrix().unwrap();
        assert_eq!((q.n_rows, q.n_cols), (4, 6));
        let mut pulled = Pulled::default();
        t.pull(bytemuck::cast_slice(&x), 3, &mut pulled);
        let mut rows = vec![0.0f32; 6 * 3];
        crate::linalg::spmv_multi(&c.view().unwrap(), &pulled.values, &mut rows, 3);
        let mut yq = vec![0.0f32; 4 * 3];
        crate::linalg::spmv_multi(&q.view().unwrap(), &rows, &mut yq, 3);
        let held = t.node_rows_pushed(&pulled.values, 3).unwrap();
        for i in 0..4 {
            let (cols, vals) = t.patch_row(i, &holders[i]);
            let by_row: f32 = cols
                .iter()
                .zip(&vals)
                .map(|(&j, &v)| v * pulled.values[j as usize * 3])
                .sum();
            let own: f32 = {
                let (cols, vals) = c.view().unwrap().row(i);
                cols.iter()
                    .zip(vals)
                    .map(|(&j, &v)| v * pulled.values[j as usize * 3])
                    .sum()
            };
            for (what, v) in [
                ("expand", yd[i][0]),
                ("patch_row", by_row),
                ("push matrix", yq[i * 3]),
                ("own row + node_rows_pushed", own + held[i * 3]),
            ] {
                assert!(
                    (v - y[i][0]).abs() < 1e-5,
                    "{what}, patch {i}: {v} vs {}",
                    y[i][0]
                );
            }
            assert!((sums[i] as f32 - ones[i][0]).abs() < 1e-6);
        }
    }

    /// S with node rows over the fixture's tree (node 0 = patches {2, 0}, node 1 = all).
    fn s_with_node_rows() -> Csr<Rgb> {
        let rows: Vec<Vec<(u32, Rgb)>> = vec![
            vec![(0, [0.1, 0.2, 0.3]), (4, [0.5, 0.4, 0.3])],
            vec![(1, [0.2, 0.1, 0.0])],
            vec![],
            vec![(5, [0.1, 0.2, 0.1])],
            // Node 0's row: a patch column and a node column.
            vec![(1, [0.3, 0.1, 0.2]), (5, [0.25, 0.5, 0.125])],
            // Node 1's row.
            vec![(4, [0.05, 0.1, 0.2])],
        ];
        Csr::from_rows(6, &rows).unwrap()
    }

    #[test]
    fn node_rows_are_pushed_to_every_patch_of_their_node() {
        let (perm, range, area, _) = fixture();
        let tree = TreeView {
            perm: &perm,
            range: &range,
        };
        let s = s_with_node_rows();
        let op = LinkedScatter::new(s.view().unwrap(), tree, &area);
        assert!(op.has_node_rows());
        let x: Vec<Rgb> = vec![
            [1.0, 0.0, 2.0],
            [2.0, 1.0, 0.0],
            [3.0, 0.0, 1.0],
            [4.0, 2.0, 0.0],
        ];
        let mut y = vec![[0.0f32; 3]; 4];
        op.apply(&x, &mut y);
        // By hand: x̄ = [x; mean of node 0; mean of node 1], each patch's row, then the rows
        // of the nodes holding it (node 0: patches 0 and 2; node 1: all four).
        let mean = |ps: &[usize]| -> [f64; 3] {
            let a: f64 = ps.iter().map(|&p| area[p] as f64).sum();
            std::array::from_fn(|c| ps.iter().map(|&p| (area[p] * x[p][c]) as f64).sum::<f64>() / a)
        };
        let mut xbar: Vec<[f64; 3]> = x.iter().map(|v| v.map(|a| a as f64)).collect();
        xbar.push(mean(&[2, 0]));
        xbar.push(mean(&[0, 1, 2, 3]));
        let row = |r: usize| -> [f64; 3] {
            let (cols, vals) = s.view().unwrap().row(r);
            std::array::from_fn(|c| {
                cols.iter()
                    .zip(vals)
                    .map(|(&i, v)| v[c] as f64 * xbar[i as usize][c])
                    .sum()
            })
        };
        let held = [vec![4, 5], vec![5], vec![4, 5], vec![5]];
        for j in 0..4 {
            let mut want = row(j);
            for &m in &held[j] {
                let v = row(m);
                for c in 0..3 {
                    want[c] += v[c];
                }
            }
            for c in 0..3 {
                assert!(
                    (y[j][c] as f64 - want[c]).abs() < 1e-6,
                    "patch {j} channel {c}: {} vs {}",
                    y[j][c],
                    want[c]
                );
            }
        }
        // Node 0's row reached patches 0 and 2 and not 1 or 3: patch 1's own row and node
        // 1's alone make its value.
        assert!(y[1][0] > 0.0);
        // Two systems side by side (6 channels) give each system's product.
        let h: Vec<f32> = x
            .iter()
            .zip(x.iter().rev())
            .flat_map(|(a, b)| a.iter().chain(b.iter()).copied())
            .collect();
        let mut y6 = vec![0.0f32; 4 * 6];
        op.apply_multi(&h, &mut y6, 6);
        let rev: Vec<Rgb> = x.iter().rev().copied().collect();
        let mut y2 = vec![[0.0f32; 3]; 4];
        op.apply(&rev, &mut y2);
        for j in 0..4 {
            for c in 0..3 {
                assert!((y6[j * 6 + c] - y[j][c]).abs() < 1e-6);
                assert!((y6[j * 6 + 3 + c] - y2[j][c]).abs() < 1e-6);
            }
        }
    }

    /// `s` with each column scaled by its factor, entry by entry.
    fn scaled(s: &Csr<Rgb>, d: &[Rgb]) -> Csr<Rgb> {
        let view = s.view().unwrap();
        let rows: Vec<Vec<(u32, Rgb)>> = (0..view.n_rows())
            .map(|j| {
                let (cols, vals) = view.row(j);
                cols.iter()
                    .zip(vals)
                    .map(|(&c, v)| (c, std::array::from_fn(|ch| v[ch] * d[c as usize][ch])))
                    .collect()
            })
            .collect();
        Csr::from_rows(s.n_cols, &rows).unwrap()
    }

    #[test]
    fn column_factors_scale_the_vector_as_they_would_scale_the_matrix() {
        let (perm, range, area, _) = fixture();
        let tree = TreeView {
            perm: &perm,
            range: &range,
        };
        let x: Vec<Rgb> = vec![
            [1.0, 0.5, 2.0],
            [2.0, 1.0, 0.25],
            [3.0, 0.0, 1.0],
            [4.0, 2.0, 0.5],
        ];
        // Patch 1 and node 1 (a node with a row and a column) scaled, in some channels.
        let d: Vec<Rgb> = vec![
            [1.0; 3],
            [0.5, 1.0, 0.25],
            [1.0; 3],
            [1.0; 3],
            [1.0; 3],
            [0.75, 0.5, 1.0],
        ];
        let close = |a: &[Rgb], b: &[Rgb]| {
            for (p, q) in a.iter().zip(b) {
                for c in 0..3 {
                    assert!((p[c] - q[c]).abs() < 1e-6, "{a:?} vs {b:?}");
                }
            }
        };
        // A hierarchical S with node rows: the factors on the pulled vector.
        let s = s_with_node_rows();
        let s_d = scaled(&s, &d);
        let (mut a, mut b) = (vec![[0.0f32; 3]; 4], vec![[0.0f32; 3]; 4]);
        LinkedScatter::new(s.view().unwrap(), tree, &area)
            .with_columns(&d)
            .apply(&x, &mut a);
        LinkedScatter::new(s_d.view().unwrap(), tree, &area).apply(&x, &mut b);
        close(&a, &b);
        // Not S on x scaled by the patches' factors first: a node's mean is of x itself
        // (a link takes its node's factor, not its patches').
        let xd: Vec<Rgb> = x
            .iter()
            .zip(&d)
            .map(|(v, f)| std::array::from_fn(|c| v[c] * f[c]))
            .collect();
        let mut naive = vec![[0.0f32; 3]; 4];
        LinkedScatter::new(s.view().unwrap(), tree, &area).apply(&xd, &mut naive);
        assert!(
            naive
                .iter()
                .zip(&a)
                .any(|(p, q)| (0..3).any(|c| (p[c] - q[c]).abs() > 1e-3)),
            "the fixture does not tell the two apart"
        );
        // A pairwise S (patch columns alone), 6 channels.
        let pair = Csr::from_rows(
            4,
            &[
                vec![(0u32, [0.2f32, 0.1, 0.3]), (1, [0.4, 0.2, 0.1])],
                vec![(1, [0.3, 0.3, 0.3]), (3, [0.1, 0.2, 0.4])],
                vec![(2, [0.5, 0.1, 0.2])],
                vec![(1, [0.2, 0.4, 0.1]), (3, [0.3, 0.2, 0.1])],
            ],
        )
        .unwrap();
        let dp = &d[..4];
        let pair_d = scaled(&pair, dp);
        let h: Vec<f32> = x
            .iter()
            .zip(x.iter().rev())
            .flat_map(|(a, b)| a.iter().chain(b.iter()).copied())
            .collect();
        let (mut a6, mut b6) = (vec![0.0f32; 24], vec![0.0f32; 24]);
        ScaledScatter {
            s: SparseScatter(pair.view().unwrap()),
            columns: dp,
        }
        .apply_multi(&h, &mut a6, 6);
        SparseScatter(pair_d.view().unwrap()).apply_multi(&h, &mut b6, 6);
        close(bytemuck::cast_slice(&a6), bytemuck::cast_slice(&b6));
    }

    #[test]
    fn node_rows_written_out_per_patch_give_the_same_products() {
        let (perm, range, area, _) = fixture();
        let tree = TreeView {
            perm: &perm,
            range: &range,
        };
        let s = s_with_node_rows();
        let pushed = push_node_rows(s.view().unwrap(), tree).unwrap();
        assert_eq!((pushed.n_rows, pushed.n_cols), (4, 6));
        // Patch 0: its row, node 0's and node 1's, column 4 summed from its own and node 1's.
        let p = pushed.view().unwrap();
        let (cols, vals) = p.row(0);
        assert_eq!(cols, &[0, 1, 4, 5]);
        assert!((vals[2][0] - 0.55).abs() < 1e-6);
        // Patch 2's own row is empty: node 0's and node 1's rows alone.
        assert_eq!(p.row(2).0, &[1, 4, 5]);
        let x: Vec<Rgb> = vec![
            [0.5, 1.0, 2.0],
            [2.0, 0.0, 1.0],
            [1.0, 3.0, 0.0],
            [0.0, 2.0, 4.0],
        ];
        let (mut a, mut b) = (vec![[0.0f32; 3]; 4], vec![[0.0f32; 3]; 4]);
        LinkedScatter::new(s.view().unwrap(), tree, &area).apply(&x, &mut a);
        let flat = LinkedScatter::new(p, tree, &area);
        assert!(!flat.has_node_rows());
        flat.apply(&x, &mut b);
        for j in 0..4 {
            for c in 0..3 {
                assert!((a[j][c] - b[j][c]).abs() < 1e-6, "{a:?} vs {b:?}");
            }
        }
        // Without node rows, S comes back as it is.
        let again = push_node_rows(p, tree).unwrap();
        assert_eq!(
            (again.row_ptr, again.col),
            (pushed.row_ptr.clone(), pushed.col.clone())
        );
    }
}
