//! Typed views of a loaded bundle's arrays beyond the CSR matrices: the environment
//! visibility, the transfer matrix and the cluster tree. Borrowed from the mapped files.

/// The environment visibility `[N, rows, cols]` as IEEE half-float bits (verified at open:
/// finite and ≥ 0); patch i's `rows · cols` bins are [`EnvVisibilityView::row`].
#[derive(Debug, Clone, Copy)]
pub struct EnvVisibilityView<'a> {
    pub rows: u32,
    pub cols: u32,
    pub bits: &'a [u16],
}

impl<'a> EnvVisibilityView<'a> {
    /// Bins per patch.
    pub fn bins(&self) -> usize {
        self.rows as usize * self.cols as usize
    }

    /// Patch i's visibility per bin (half-float bits).
    pub fn row(&self, i: usize) -> &'a [u16] {
        let k = self.bins();
        &self.bits[k * i..k * (i + 1)]
    }
}

/// The stored transfer matrix R = T − S (see the layout above): `bits` holds IEEE half
/// floats `[N, N, 3]` as raw bits, `scale` the per-row, per-channel factors.
#[derive(Debug, Clone, Copy)]
pub struct TransferView<'a> {
    pub n: usize,
    pub bits: &'a [u16],
    pub scale: &'a [[f32; 3]],
}

impl<'a> TransferView<'a> {
    /// Row j: 3N half-float bits (column k, channel c at 3k + c).
    pub fn row(&self, j: usize) -> &'a [u16] {
        &self.bits[3 * self.n * j..3 * self.n * (j + 1)]
    }
}

// Array files are raw little-endian and cast in place: a big-endian build would read garbage.
#[cfg(target_endian = "big")]
compile_error!(
    "translux bundles hold little-endian arrays that are cast in place; big-endian targets are not supported"
);

/// The cluster tree of a hierarchical F ([`Bundle::tree`]): node k covers the patches
/// `perm[range[k][0]..range[k][1]]`.
#[derive(Debug, Clone, Copy)]
pub struct TreeView<'a> {
    pub perm: &'a [u32],
    pub range: &'a [[u32; 2]],
}
