//! Typed views of a loaded bundle's arrays beyond the CSR matrices: the environment
//! visibility, the transfer matrix, the cluster tree and the walks of a simulated S.
//! Borrowed from the mapped files.

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

/// The cluster tree of a hierarchical F ([`Bundle::tree`](super::Bundle::tree)): node k covers the patches
/// `perm[range[k][0]..range[k][1]]`.
#[derive(Debug, Clone, Copy)]
pub struct TreeView<'a> {
    pub perm: &'a [u32],
    pub range: &'a [[u32; 2]],
}

/// Bins per doubling of path length in the walks of a simulated S: a bin spans 2^(1/16).
pub const SIM_BINS_PER_OCTAVE: u32 = 16;
/// The lower edge of bin 0 (mm); shorter paths fall into bin 0.
pub const SIM_BIN_L0_MM: f64 = 1e-4;
/// Number of path-length bins: 64 doublings above 0.1 µm.
pub const SIM_BINS: u32 = 64 * SIM_BINS_PER_OCTAVE;
/// Set in a record's `sim_bin` (version 8 on): its walks entered diffusely and left without
/// scattering (U, which lamps leave out); the bin is the rest of the bits.
pub const SIM_UNSCATTERED: u32 = 1 << 31;
/// Fixed-point scale of the tilt ratios in `sim_weight_lamp` (i16, ±1 = ±32767).
pub const SIM_TILT_ONE: f32 = 32767.0;

/// The stored random walks of simulated objects ([`Bundle::walks`](crate::bundle::Bundle::walks)):
/// row j (a receiver patch) holds records sorted by source patch i, then by bin; a record's
/// `weight` is its walks' share of S_ji at zero absorption, and
/// S_ji = Σ_records w · e^(−σa L_bin), L_bin = `SIM_BIN_L0_MM` · 2^((bin + ½)/16) mm.
/// `normal` (bundles from version 7 on) is the same for light entering collimated along the
/// inward normal; it may be below or above `weight`. `lamp` (version 8 on) is the
/// records' G_u and G_v (the first harmonic of S_ji in the tilt of collimated light
/// entering i), per channel as two i16 ratios to 4 `weight` packed in a u32
/// (`arrays::SIM_WEIGHT_LAMP`); records whose bin has [`SIM_UNSCATTERED`] are U.
#[derive(Debug, Clone, Copy)]
pub struct WalksView<'a> {
    pub row_ptr: &'a [u64],
    pub col: &'a [u32],
    pub bin: &'a [u32],
    pub weight: &'a [[f32; 3]],
    pub normal: Option<&'a [[f32; 3]]>,
    pub lamp: Option<&'a [[u32; 3]]>,
}

impl<'a> WalksView<'a> {
    /// Checks the arrays: `n` rows, increasing pointers that end at the record count,
    /// sources below `n`, bins below [`SIM_BINS`], weights finite and ≥ 0.
    pub fn new_checked(
        n: usize,
        row_ptr: &'a [u64],
        col: &'a [u32],
        bin: &'a [u32],
        weight: &'a [[f32; 3]],
        normal: Option<&'a [[f32; 3]]>,
    ) -> Result<Self, String> {
        if row_ptr.len() != n + 1 {
            return Err(format!(
                "sim_row_ptr has {} entries, expected {} (N + 1)",
                row_ptr.len(),
                n + 1
            ));
        }
        let m = col.len();
        if bin.len() != m || weight.len() != m {
            return Err("sim_col, sim_bin and sim_weight differ in length".into());
        }
        if row_ptr[0] != 0 || row_ptr[n] != m as u64 || row_ptr.windows(2).any(|w| w[0] > w[1]) {
            return Err("sim_row_ptr is not increasing from 0 to the record count".into());
        }
        if let Some(k) = col.iter().position(|&c| c as usize >= n) {
            return Err(format!("sim_col[{k}] = {} is not a patch", col[k]));
        }
        if let Some(k) = bin.iter().position(|&b| b & !SIM_UNSCATTERED >= SIM_BINS) {
            return Err(format!(
                "sim_bin[{k}] = {} is not a bin (< {SIM_BINS})",
                bin[k]
            ));
        }
        if let Some(k) = weight
            .iter()
            .position(|w| w.iter().any(|v| !v.is_finite() || *v < 0.0))
        {
            return Err(format!("sim_weight[{k}] is negative or not finite"));
        }
        if let Some(normal) = normal {
            if normal.len() != m {
                return Err("sim_weight_normal and sim_weight differ in length".into());
            }
            if let Some(k) = normal
                .iter()
                .position(|w| w.iter().any(|v| !v.is_finite() || *v < 0.0))
            {
                return Err(format!("sim_weight_normal[{k}] is negative or not finite"));
            }
        }
        Ok(Self {
            row_ptr,
            col,
            bin,
            weight,
            normal,
            lamp: None,
        })
    }

    /// The view with lamp weights (`sim_weight_lamp`), checked: one per record, and only
    /// beside collimated weights (every bit pattern is a ratio in [−1, 1]).
    pub fn with_lamp(mut self, lamp: &'a [[u32; 3]]) -> Result<Self, String> {
        if self.normal.is_none() {
            return Err("sim_weight_lamp without sim_weight_normal".into());
        }
        if lamp.len() != self.col.len() {
            return Err("sim_weight_lamp and sim_weight differ in length".into());
        }
        self.lamp = Some(lamp);
        Ok(self)
    }

    /// Row j's records: sources, bins, weights.
    pub fn row(&self, j: usize) -> (&'a [u32], &'a [u32], &'a [[f32; 3]]) {
        let (a, b) = (self.row_ptr[j] as usize, self.row_ptr[j + 1] as usize);
        (&self.col[a..b], &self.bin[a..b], &self.weight[a..b])
    }

    /// Row j's collimated-entry weights (`None` for a bundle older than version 7).
    pub fn row_normal(&self, j: usize) -> Option<&'a [[f32; 3]]> {
        let (a, b) = (self.row_ptr[j] as usize, self.row_ptr[j + 1] as usize);
        self.normal.map(|w| &w[a..b])
    }

    /// Row j's lamp weights (`None` for a bundle older than version 8).
    pub fn row_lamp(&self, j: usize) -> Option<&'a [[u32; 3]]> {
        let (a, b) = (self.row_ptr[j] as usize, self.row_ptr[j + 1] as usize);
        self.lamp.map(|w| &w[a..b])
    }
}
