//! Compressed sparse rows: the layout of F (and later S) on disk and in memory.
//!
//! Rows are receivers: row `i` lists the patches `j` that patch `i` sees, with F_ij.
//!
//! ```text
//!             row_ptr (u64, n+1)        col (u32, nnz)     val (f32, nnz)
//!  row 0  ->  row_ptr[0] = 0         -> col[0..3] = 4 7 9   val[0..3] = F_04 F_07 F_09
//!  row 1  ->  row_ptr[1] = 3         -> col[3..5] = 0 2     val[3..5] = F_10 F_12
//!  ...
//!  end        row_ptr[n] = nnz
//! ```
//!
//! Column indices are strictly increasing within a row.

use thiserror::Error;

/// Why a set of arrays is not a valid CSR matrix.
#[derive(Debug, Error, PartialEq)]
pub enum CsrError {
    #[error("row_ptr has {got} entries, expected rows + 1 = {expected}")]
    RowPtrLength { got: usize, expected: usize },
    #[error("row_ptr[0] is {0}, expected 0")]
    RowPtrStart(u64),
    #[error("row_ptr decreases at row {row}")]
    RowPtrDecreasing { row: usize },
    #[error("row_ptr ends at {end} but there are {col} column indices and {val} values")]
    NnzMismatch { end: u64, col: usize, val: usize },
    #[error("row {row}: column {col} is out of range (columns: {n_cols})")]
    ColumnOutOfRange { row: usize, col: u32, n_cols: usize },
    #[error("row {row}: columns are not strictly increasing at column {col}")]
    ColumnsUnsorted { row: usize, col: u32 },
    #[error("row {row}, column {col}: a value is not finite")]
    NonFinite { row: usize, col: u32 },
}

/// A value a CSR matrix can hold: a scalar (F, distances) or an RGB triple (S).
pub trait CsrValue: Copy + std::fmt::Debug {
    /// Every component is finite.
    fn is_finite_value(&self) -> bool;

    /// Every value of `values` is finite.
    fn all_finite(values: &[Self]) -> bool {
        values.iter().all(Self::is_finite_value)
    }
}

/// Every value finite: a branch-free pass that the compiler vectorises (a check of millions
/// of values after every rewrite of S).
fn all_finite_f32(values: &[f32]) -> bool {
    values
        .chunks(1024)
        .all(|c| c.iter().fold(true, |ok, v| ok & v.is_finite()))
}

impl CsrValue for f32 {
    fn is_finite_value(&self) -> bool {
        self.is_finite()
    }

    fn all_finite(values: &[Self]) -> bool {
        all_finite_f32(values)
    }
}

/// Six RGB values per entry (the tilt of a simulated S: Δ, G_u, G_v, U and U's G_u, G_v).
impl CsrValue for [[f32; 3]; 6] {
    fn is_finite_value(&self) -> bool {
        self.iter().flatten().all(|v| v.is_finite())
    }

    fn all_finite(values: &[Self]) -> bool {
        all_finite_f32(values.as_flattened().as_flattened())
    }
}

impl CsrValue for [f32; 3] {
    fn is_finite_value(&self) -> bool {
        self.iter().all(|v| v.is_finite())
    }

    fn all_finite(values: &[Self]) -> bool {
        all_finite_f32(values.as_flattened())
    }
}

/// A CSR matrix's column indices in 16 bits: each entry's column less its block's start
/// (blocks of 65,536 columns), and where each row's entries of every block after the first
/// begin. The columns of a row ascend, so its entries of one block are contiguous and a
/// product that walks the blocks in order reads them in the row's own order.
///
/// Made in memory from a checked [`CsrView`] (the bundle keeps the full u32 columns): a
/// product over F reads 6 bytes an entry instead of 8, and F's product is bound by the
/// bytes it streams (bench/results/HISTORY.md).
#[derive(Debug, Clone, PartialEq)]
pub struct NarrowCols {
    /// Blocks of 65,536 columns: at least 1.
    blocks: usize,
    /// Each entry's column less 65,536 × its block.
    low: Vec<u16>,
    /// Per row, `blocks − 1` offsets within the row: where blocks 1, 2, … begin.
    starts: Vec<u32>,
}

impl NarrowCols {
    /// Columns per block.
    pub const BLOCK: usize = 1 << 16;

    /// The narrow columns of `m`.
    pub fn of<T: CsrValue>(m: &CsrView<'_, T>) -> NarrowCols {
        let blocks = m.n_cols().div_ceil(Self::BLOCK).max(1);
        let mut starts = Vec::with_capacity(m.n_rows() * (blocks - 1));
        for i in 0..m.n_rows() {
            let (cols, _) = m.row(i);
            // Entries of a row ascend by column: block b begins at the first column ≥ b·65,536.
            for b in 1..blocks {
                let at = cols.partition_point(|&c| (c as usize) < b * Self::BLOCK);
                starts.push(at as u32);
            }
        }
        NarrowCols {
            blocks,
            low: m.col().iter().map(|&c| c as u16).collect(),
            starts,
        }
    }

    /// Blocks of 65,536 columns.
    pub fn blocks(&self) -> usize {
        self.blocks
    }

    /// Entries (as the matrix they were made from).
    pub fn nnz(&self) -> usize {
        self.low.len()
    }

    /// Row `i`'s entries, from `first` (its start in the matrix) to `end`, as runs of one
    /// block each in column order: `f(base, range)` with the block's first column and the
    /// run's entries (absolute indices, into [`NarrowCols::low`] and the matrix's values).
    #[inline]
    pub fn for_each_run(
        &self,
        i: usize,
        first: usize,
        end: usize,
        mut f: impl FnMut(usize, std::ops::Range<usize>),
    ) {
        let starts = &self.starts[i * (self.blocks - 1)..(i + 1) * (self.blocks - 1)];
        let mut at = first;
        for (b, &s) in starts.iter().enumerate() {
            let next = first + s as usize;
            if next > at {
                f(b * Self::BLOCK, at..next);
            }
            at = next;
        }
        if end > at {
            f((self.blocks - 1) * Self::BLOCK, at..end);
        }
    }

    /// Each entry's column less its block's start.
    pub fn low(&self) -> &[u16] {
        &self.low
    }
}

/// A borrowed CSR matrix, checked once at construction and trusted afterwards.
#[derive(Debug, Clone, Copy)]
pub struct CsrView<'a, T: CsrValue = f32> {
    n_rows: usize,
    n_cols: usize,
    row_ptr: &'a [u64],
    col: &'a [u32],
    val: &'a [T],
}

impl<'a, T: CsrValue> CsrView<'a, T> {
    /// Wraps the three arrays after checking every invariant: row_ptr length n+1, starting
    /// at 0, non-decreasing, ending at nnz; columns in range and strictly increasing per
    /// row; values finite. Costs one pass over the matrix.
    pub fn new_checked(
        n_rows: usize,
        n_cols: usize,
        row_ptr: &'a [u64],
        col: &'a [u32],
        val: &'a [T],
    ) -> Result<Self, CsrError> {
        if row_ptr.len() != n_rows + 1 {
            return Err(CsrError::RowPtrLength {
                got: row_ptr.len(),
                expected: n_rows + 1,
            });
        }
        if row_ptr[0] != 0 {
            return Err(CsrError::RowPtrStart(row_ptr[0]));
        }
        let end = row_ptr[n_rows];
        if end as usize != col.len() || col.len() != val.len() {
            return Err(CsrError::NnzMismatch {
                end,
                col: col.len(),
                val: val.len(),
            });
        }
        for row in 0..n_rows {
            let (a, b) = (row_ptr[row], row_ptr[row + 1]);
            if b < a || b > end {
                return Err(CsrError::RowPtrDecreasing { row });
            }
            let cols = &col[a as usize..b as usize];
            let vals = &val[a as usize..b as usize];
            for (k, (&c, &v)) in cols.iter().zip(vals).enumerate() {
                if c as usize >= n_cols {
                    return Err(CsrError::ColumnOutOfRange {
                        row,
                        col: c,
                        n_cols,
                    });
                }
                if k > 0 && c <= cols[k - 1] {
                    return Err(CsrError::ColumnsUnsorted { row, col: c });
                }
                if !v.is_finite_value() {
                    return Err(CsrError::NonFinite { row, col: c });
                }
            }
        }
        Ok(Self {
            n_rows,
            n_cols,
            row_ptr,
            col,
            val,
        })
    }

    /// Wraps arrays that already passed [`CsrView::new_checked`] with the same `n_rows` and
    /// `n_cols` (the bundle loader checks once at open and hands out views afterwards without
    /// another pass over the matrix). Crate-internal so that the invariants stay guaranteed.
    pub(crate) fn from_checked_parts(
        n_rows: usize,
        n_cols: usize,
        row_ptr: &'a [u64],
        col: &'a [u32],
        val: &'a [T],
    ) -> Self {
        Self {
            n_rows,
            n_cols,
            row_ptr,
            col,
            val,
        }
    }

    pub fn n_rows(&self) -> usize {
        self.n_rows
    }
    pub fn n_cols(&self) -> usize {
        self.n_cols
    }
    pub fn nnz(&self) -> usize {
        self.col.len()
    }
    pub fn row_ptr(&self) -> &'a [u64] {
        self.row_ptr
    }
    pub fn col(&self) -> &'a [u32] {
        self.col
    }
    pub fn val(&self) -> &'a [T] {
        self.val
    }

    /// The columns and values of row `i`.
    #[inline]
    pub fn row(&self, i: usize) -> (&'a [u32], &'a [T]) {
        let (a, b) = (self.row_ptr[i] as usize, self.row_ptr[i + 1] as usize);
        (&self.col[a..b], &self.val[a..b])
    }

    /// The entry (i, j), or `None` when it is not stored.
    pub fn entry(&self, i: usize, j: usize) -> Option<T> {
        let (cols, vals) = self.row(i);
        cols.binary_search(&(j as u32)).ok().map(|k| vals[k])
    }
}

impl CsrView<'_, f32> {
    /// The entry (i, j), or 0 when it is not stored.
    pub fn get(&self, i: usize, j: usize) -> f32 {
        self.entry(i, j).unwrap_or(0.0)
    }
}

/// An owned CSR matrix over values `T` (F and distances: `f32`; S: RGB): what the
/// precompute builds before writing it, and what S assembly hands the backends. The one
/// owned CSR type of the workspace; build it row by row with [`CsrBuilder`] (each row
/// checked as it is pushed) or [`Csr::from_rows`], and borrow it with [`Csr::view`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Csr<T: CsrValue = f32> {
    pub n_rows: usize,
    pub n_cols: usize,
    pub row_ptr: Vec<u64>,
    pub col: Vec<u32>,
    pub val: Vec<T>,
}

impl<T: CsrValue> Csr<T> {
    /// Borrows it as a checked view (one pass over the matrix).
    pub fn view(&self) -> Result<CsrView<'_, T>, CsrError> {
        CsrView::new_checked(
            self.n_rows,
            self.n_cols,
            &self.row_ptr,
            &self.col,
            &self.val,
        )
    }

    pub fn nnz(&self) -> usize {
        self.col.len()
    }

    /// The matrix with `n_cols` columns whose row i lists `rows[i]`'s (column, value)
    /// pairs, each row checked as by [`CsrBuilder::push_row`].
    pub fn from_rows(
        n_cols: usize,
        rows: impl IntoIterator<Item = impl AsRef<[(u32, T)]>>,
    ) -> Result<Self, CsrError> {
        let mut b = CsrBuilder::new(n_cols);
        for row in rows {
            b.push_row(row.as_ref())?;
        }
        Ok(b.finish())
    }
}

/// Builds a [`Csr`] a row at a time, checking each row as it comes: columns in range and
/// strictly increasing, values finite. What it finishes is therefore always a valid matrix.
#[derive(Debug, Clone)]
pub struct CsrBuilder<T: CsrValue = f32> {
    csr: Csr<T>,
}

impl<T: CsrValue> CsrBuilder<T> {
    /// An empty matrix of `n_cols` columns (no rows yet).
    pub fn new(n_cols: usize) -> Self {
        CsrBuilder {
            csr: Csr {
                n_rows: 0,
                n_cols,
                row_ptr: vec![0],
                col: Vec::new(),
                val: Vec::new(),
            },
        }
    }

    /// Reserves room for `rows` more rows and `nnz` more entries.
    pub fn reserve(&mut self, rows: usize, nnz: usize) {
        self.csr.row_ptr.reserve(rows);
        self.csr.col.reserve(nnz);
        self.csr.val.reserve(nnz);
    }

    /// Rows pushed so far.
    pub fn rows(&self) -> usize {
        self.csr.n_rows
    }

    /// Entries pushed so far.
    pub fn nnz(&self) -> usize {
        self.csr.col.len()
    }

    /// Appends the next row; on an invalid row nothing is appended and the error names the
    /// row and the column.
    pub fn push_row(&mut self, entries: &[(u32, T)]) -> Result<(), CsrError> {
        let row = self.csr.n_rows;
        for (k, &(c, v)) in entries.iter().enumerate() {
            if c as usize >= self.csr.n_cols {
                return Err(CsrError::ColumnOutOfRange {
                    row,
                    col: c,
                    n_cols: self.csr.n_cols,
                });
            }
            if k > 0 && c <= entries[k - 1].0 {
                return Err(CsrError::ColumnsUnsorted { row, col: c });
            }
            if !v.is_finite_value() {
                return Err(CsrError::NonFinite { row, col: c });
            }
        }
        self.csr.col.extend(entries.iter().map(|e| e.0));
        self.csr.val.extend(entries.iter().map(|e| e.1));
        self.csr.row_ptr.push(self.csr.col.len() as u64);
        self.csr.n_rows += 1;
        Ok(())
    }

    pub fn finish(self) -> Csr<T> {
        self.csr
    }
}

/// An owned CSR matrix whose invariants hold (checked once, or built row by row by
/// [`CsrBuilder`]): its views cost nothing, and its values can be rewritten in place with
/// its pattern fixed ([`ValidCsr::rewrite`]), which is how a translucency change writes a
/// new S without building its rows again.
#[derive(Debug, Clone)]
pub struct ValidCsr<T: CsrValue = f32> {
    csr: Csr<T>,
}

impl<T: CsrValue> ValidCsr<T> {
    /// Checks `csr` (one pass over the matrix).
    pub fn new(csr: Csr<T>) -> Result<Self, CsrError> {
        csr.view()?;
        Ok(ValidCsr { csr })
    }

    /// The matrix as a view, with no pass over it.
    pub fn view(&self) -> CsrView<'_, T> {
        let c = &self.csr;
        CsrView::from_checked_parts(c.n_rows, c.n_cols, &c.row_ptr, &c.col, &c.val)
    }

    /// The matrix's arrays.
    pub fn csr(&self) -> &Csr<T> {
        &self.csr
    }

    pub fn into_csr(self) -> Csr<T> {
        self.csr
    }

    /// Rewrites the values of rows `rows` in place: `write` gets each of those rows as
    /// (its columns, its values), in order, and may set the values; the columns stay. The
    /// values written are then checked finite; on a non-finite one the matrix is dropped and
    /// the error names the row and the column.
    pub fn rewrite(
        self,
        rows: std::ops::Range<usize>,
        write: impl FnOnce(Vec<(&[u32], &mut [T])>),
    ) -> Result<Self, CsrError> {
        self.rewrite_vouched(rows, |r| {
            write(r);
            false
        })
    }

    /// [`ValidCsr::rewrite`] for a writer that checks each value as it stores it: `write`
    /// answers whether every value it stored was finite, and then the rows are not read
    /// again (the values it left alone were finite already: the matrix was valid). On
    /// `false` they are checked as `rewrite` checks them. Rewriting the bunny's S (525 MB of
    /// values) spent about 7% of the rewrite in that second read.
    pub fn rewrite_vouched(
        self,
        rows: std::ops::Range<usize>,
        write: impl FnOnce(Vec<(&[u32], &mut [T])>) -> bool,
    ) -> Result<Self, CsrError> {
        self.rewrite_ranges_vouched(std::slice::from_ref(&rows), write)
    }

    /// [`ValidCsr::rewrite_vouched`] for the rows of several ranges, ascending and apart
    /// (an object's patch rows and its node rows): `write` gets every row of them in that
    /// order.
    pub fn rewrite_ranges_vouched(
        mut self,
        ranges: &[std::ops::Range<usize>],
        write: impl FnOnce(Vec<(&[u32], &mut [T])>) -> bool,
    ) -> Result<Self, CsrError> {
        let c = &mut self.csr;
        for (k, r) in ranges.iter().enumerate() {
            assert!(
                r.start <= r.end && r.end <= c.n_rows,
                "rows {r:?} of {} rows",
                c.n_rows
            );
            if let Some(next) = ranges.get(k + 1) {
                assert!(
                    r.end <= next.start,
                    "ranges {r:?} and {next:?} out of order"
                );
            }
        }
        let (Some(lo), Some(hi)) = (ranges.first(), ranges.last()) else {
            write(Vec::new());
            return Ok(self);
        };
        let (lo, hi) = (lo.start, hi.end);
        let first = c.row_ptr[lo] as usize;
        let (mut vals, mut cols) = (
            &mut c.val[first..c.row_ptr[hi] as usize],
            &c.col[first..c.row_ptr[hi] as usize],
        );
        let mut split = Vec::with_capacity(ranges.iter().map(|r| r.len()).sum());
        let mut at = lo;
        for r in ranges {
            // The rows between ranges are passed over.
            let gap = (c.row_ptr[r.start] - c.row_ptr[at]) as usize;
            vals = std::mem::take(&mut vals).split_at_mut(gap).1;
            cols = cols.split_at(gap).1;
            for row in r.clone() {
                let len = (c.row_ptr[row + 1] - c.row_ptr[row]) as usize;
                let (v, rest) = std::mem::take(&mut vals).split_at_mut(len);
                let (k, more) = cols.split_at(len);
                split.push((k, v));
                (vals, cols) = (rest, more);
            }
            at = r.end;
        }
        if write(split) {
            return Ok(self);
        }
        for r in ranges {
            let written = c.row_ptr[r.start] as usize..c.row_ptr[r.end] as usize;
            if T::all_finite(&c.val[written]) {
                continue;
            }
            for row in r.clone() {
                let (a, b) = (c.row_ptr[row] as usize, c.row_ptr[row + 1] as usize);
                if let Some(k) = c.val[a..b].iter().position(|v| !v.is_finite_value()) {
                    return Err(CsrError::NonFinite {
                        row,
                        col: c.col[a + k],
                    });
                }
            }
        }
        Ok(self)
    }
}

impl<T: CsrValue> CsrBuilder<T> {
    /// The matrix built, valid by construction (every row was checked as it came).
    pub fn finish_valid(self) -> ValidCsr<T> {
        ValidCsr { csr: self.csr }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Narrow columns give back every column, in the row's order, over blocks some rows
    /// skip, with empty rows and a matrix of one block.
    #[test]
    fn narrow_columns_give_back_every_column_in_order() {
        for n_cols in [5usize, 65_536, 65_537, 200_000] {
            let mut state = 11u64;
            let mut next = || {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 33) as usize
            };
            let (mut rp, mut col) = (vec![0u64], Vec::new());
            for row in 0..40 {
                let mut cols: Vec<u32> = if row % 7 == 3 {
                    Vec::new()
                } else {
                    (0..next() % 30).map(|_| (next() % n_cols) as u32).collect()
                };
                if row == 5 {
                    cols.push((n_cols - 1) as u32);
                }
                cols.sort();
                cols.dedup();
                col.extend(&cols);
                rp.push(col.len() as u64);
            }
            let val = vec![1.0f32; col.len()];
            let m = CsrView::new_checked(40, n_cols, &rp, &col, &val).unwrap();
            let narrow = NarrowCols::of(&m);
            assert_eq!(narrow.blocks(), n_cols.div_ceil(65_536));
            assert_eq!(narrow.nnz(), col.len());
            for i in 0..40 {
                let (a, b) = (rp[i] as usize, rp[i + 1] as usize);
                let mut got = Vec::new();
                let mut at = a;
                narrow.for_each_run(i, a, b, |base, run| {
                    assert_eq!(run.start, at, "runs are contiguous");
                    at = run.end;
                    got.extend(run.map(|e| (base + narrow.low()[e] as usize) as u32));
                });
                assert_eq!(at, b, "runs reach the row's end");
                assert_eq!(got, col[a..b], "row {i} of {n_cols} columns");
            }
        }
    }

    #[test]
    fn checked_view_accepts_valid_and_names_each_violation() {
        let rp = [0u64, 2, 3];
        let col = [0u32, 2, 1];
        let val = [0.5f32, 0.25, 1.0];
        let v = CsrView::new_checked(2, 3, &rp, &col, &val).unwrap();
        assert_eq!(v.get(0, 2), 0.25);
        assert_eq!(v.get(1, 0), 0.0);
        assert_eq!(
            CsrView::new_checked(2, 2, &rp, &col, &val).unwrap_err(),
            CsrError::ColumnOutOfRange {
                row: 0,
                col: 2,
                n_cols: 2
            }
        );
        let unsorted = [2u32, 0, 1];
        assert!(matches!(
            CsrView::new_checked(2, 3, &rp, &unsorted, &val),
            Err(CsrError::ColumnsUnsorted { row: 0, .. })
        ));
        let nan = [0.5f32, f32::NAN, 1.0];
        assert!(matches!(
            CsrView::new_checked(2, 3, &rp, &col, &nan),
            Err(CsrError::NonFinite { .. })
        ));
        assert!(matches!(
            CsrView::new_checked(3, 3, &[0, 2, 1, 2], &col[..2], &val[..2]),
            Err(CsrError::RowPtrDecreasing { row: 1 })
        ));
        assert!(matches!(
            CsrView::new_checked(3, 3, &rp, &col, &val),
            Err(CsrError::RowPtrLength { .. })
        ));
    }

    #[test]
    fn the_builder_checks_each_row_and_keeps_the_matrix_valid() {
        let mut b = CsrBuilder::<f32>::new(4);
        b.push_row(&[(0, 1.0), (3, 2.0)]).unwrap();
        b.push_row(&[]).unwrap();
        assert_eq!(
            b.push_row(&[(2, 1.0), (1, 1.0)]),
            Err(CsrError::ColumnsUnsorted { row: 2, col: 1 })
        );
        assert_eq!(
            b.push_row(&[(4, 1.0)]),
            Err(CsrError::ColumnOutOfRange {
                row: 2,
                col: 4,
                n_cols: 4
            })
        );
        assert_eq!(
            b.push_row(&[(1, f32::NAN)]),
            Err(CsrError::NonFinite { row: 2, col: 1 })
        );
        b.push_row(&[(1, 5.0)]).unwrap();
        let m = b.finish();
        assert_eq!((m.n_rows, m.nnz()), (3, 3));
        let v = m.view().unwrap();
        assert_eq!(v.get(0, 3), 2.0);
        assert_eq!(v.get(2, 1), 5.0);
        let rgb = Csr::<[f32; 3]>::from_rows(2, [vec![(1, [1.0, 2.0, 3.0])], vec![]]).unwrap();
        assert_eq!(rgb.view().unwrap().entry(0, 1), Some([1.0, 2.0, 3.0]));
        assert!(Csr::<[f32; 3]>::from_rows(2, [vec![(0, [f32::INFINITY, 0.0, 0.0])]]).is_err());
    }

    #[test]
    fn rows_of_several_ranges_are_rewritten_and_the_rows_between_left_alone() {
        let mut b = CsrBuilder::<f32>::new(4);
        for r in 0..5 {
            b.push_row(&[(r % 4, r as f32 + 1.0)]).unwrap();
        }
        let m = b
            .finish_valid()
            .rewrite_ranges_vouched(&[0..1, 2..2, 3..5], |rows| {
                assert_eq!(rows.len(), 3);
                assert_eq!(rows.iter().map(|r| r.0[0]).collect::<Vec<_>>(), [0, 3, 0]);
                rows.into_iter().for_each(|(_, v)| v[0] *= 10.0);
                true
            })
            .unwrap();
        assert_eq!(m.view().val(), &[10.0, 2.0, 3.0, 40.0, 50.0]);
        // Unvouched, a non-finite value in a later range is named by its row.
        let err = m
            .rewrite_ranges_vouched(&[1..2, 4..5], |mut rows| {
                rows[1].1[0] = f32::INFINITY;
                false
            })
            .unwrap_err();
        assert_eq!(err, CsrError::NonFinite { row: 4, col: 0 });
    }

    #[test]
    fn a_valid_matrix_rewrites_its_values_and_refuses_non_finite_ones() {
        let mut b = CsrBuilder::<f32>::new(3);
        b.push_row(&[(0, 1.0), (2, 2.0)]).unwrap();
        b.push_row(&[]).unwrap();
        b.push_row(&[(1, 3.0)]).unwrap();
        let m = b.finish_valid();
        let m = m
            .rewrite(1..3, |rows| {
                assert_eq!(rows.len(), 2);
                assert!(rows[0].0.is_empty());
                assert_eq!(rows[1].0, &[1]);
                rows.into_iter()
                    .for_each(|(_, v)| v.iter_mut().for_each(|x| *x *= 10.0));
            })
            .unwrap();
        assert_eq!(m.view().val(), &[1.0, 2.0, 30.0]);
        assert_eq!(m.view().col(), &[0, 2, 1]);
        let err = m
            .rewrite(0..1, |mut rows| rows[0].1[1] = f32::NAN)
            .unwrap_err();
        assert_eq!(err, CsrError::NonFinite { row: 0, col: 2 });
        // A writer that vouches for its values is not checked again; one that does not is.
        let mut b = CsrBuilder::<f32>::new(2);
        b.push_row(&[(0, 1.0)]).unwrap();
        b.push_row(&[(1, 2.0)]).unwrap();
        let m = b
            .finish_valid()
            .rewrite_vouched(0..2, |mut rows| {
                rows[1].1[0] = 5.0;
                true
            })
            .unwrap();
        assert_eq!(m.view().val(), &[1.0, 5.0]);
        let err = m
            .rewrite_vouched(1..2, |mut rows| {
                rows[0].1[0] = f32::INFINITY;
                false
            })
            .unwrap_err();
        assert_eq!(err, CsrError::NonFinite { row: 1, col: 1 });
        let bad = Csr {
            n_rows: 1,
            n_cols: 1,
            row_ptr: vec![0, 1],
            col: vec![1],
            val: vec![0.0f32],
        };
        assert!(ValidCsr::new(bad).is_err());
    }
}
