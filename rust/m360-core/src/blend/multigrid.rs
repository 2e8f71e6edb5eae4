//! Geometric multigrid V-cycle on the ERP grid: the preconditioner of the Poisson blend's CG.
//!
//! The system is A = L_W + M: a weighted graph Laplacian on the 4-neighbour ERP grid (periodic
//! in longitude, no edge across a pole) plus a positive diagonal M (λ at seen pixels, 1 at
//! unseen ones). Coarse grids aggregate 2×2 pixels: the coarse mass is the sum of the four fine
//! masses, a coarse edge weight is `COARSE_EDGE_SCALE` times the sum of the fine edges crossing
//! between two aggregates, restriction sums the residual over an aggregate and prolongation
//! copies the coarse correction to its four pixels (restriction = prolongationᵀ). Because λ
//! stays fixed while the Laplacian's share of the diagonal halves from grid to grid, a few
//! levels make the coarse system diagonally dominant and Jacobi sweeps solve it.
//!
//! The smoother is red-black Gauss–Seidel (pixels with i + j even are red): red then black
//! before the coarse correction, black then red after it, so the V-cycle is a symmetric
//! positive definite operator whatever the coarse grids hold (CG needs exactly that). Starting
//! from zero, every half sweep's result depends only on the other colour, which lets each
//! V-cycle run in two passes over a level (see [`v_cycle`]). Everything is f32
//! (a preconditioner only has to be a good approximation); the chunking is fixed, so the result
//! does not depend on the number of threads.

use rayon::prelude::*;

/// Scale of summed fine edges on the coarse grid. 1 is the Galerkin operator of piecewise-
/// constant prolongation, which is about twice too stiff for smooth errors (an aggregate
/// boundary carries two fine edges between cells twice as far apart); 0.5 is the re-discretised
/// operator.
const COARSE_EDGE_SCALE: f32 = 0.5;
/// Rows per parallel work item.
const ROWS: usize = 8;
/// Stop coarsening at this many rows (or when a dimension is odd).
const MIN_ROWS: usize = 8;
/// Damped Jacobi on the coarsest grid: ω below 1 keeps the sweep polynomial positive on the
/// spectrum of D⁻¹A, which lies in (0, 2) for a diagonally dominant matrix.
const COARSE_OMEGA: f32 = 0.8;
const COARSE_SWEEPS: usize = 16;

/// A value the V-cycle reads as a right-hand side (f64 CG residual on the finest grid, f32 on
/// the coarse ones).
pub(super) trait Rhs: Copy + Send + Sync {
    fn get(self) -> f32;
}
impl Rhs for f32 {
    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    fn get(self) -> f32 {
        self
    }
}
impl Rhs for f64 {
    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    fn get(self) -> f32 {
        self as f32
    }
}

/// The operator of one grid: edge weights and the inverse diagonal.
#[derive(Debug)]
struct Grid {
    height: usize,
    width: usize,
    /// Edge to the right neighbour (wrapping).
    right: Vec<f32>,
    /// Edge to the pixel below (0 on the last row).
    down: Vec<f32>,
    inv_diag: Vec<f32>,
}

/// One coarse grid with its right-hand side and solution.
#[derive(Debug)]
struct Coarse {
    grid: Grid,
    b: Vec<f32>,
    x: Vec<f32>,
}

/// The hierarchy below the finest grid, whose edges stay in the Poisson system.
#[derive(Debug)]
pub(super) struct Multigrid {
    height: usize,
    width: usize,
    fine_inv_diag: Vec<f32>,
    coarse: Vec<Coarse>,
}

/// Borrowed operator of a grid.
#[derive(Clone, Copy)]
struct Op<'a> {
    height: usize,
    width: usize,
    right: &'a [f32],
    down: &'a [f32],
    inv_diag: &'a [f32],
}

impl Grid {
    fn op(&self) -> Op<'_> {
        Op {
            height: self.height,
            width: self.width,
            right: &self.right,
            down: &self.down,
            inv_diag: &self.inv_diag,
        }
    }
}

/// Whether an H×W grid is coarsened further (2×2 aggregates need even sizes; red-black
/// colouring needs an even width so that the longitude wrap joins different colours).
fn coarsens(height: usize, width: usize) -> bool {
    height.is_multiple_of(2) && width.is_multiple_of(4) && height / 2 >= MIN_ROWS
}

impl Multigrid {
    /// Whether the V-cycle applies to an H×W grid (red-black needs an even width).
    pub(super) fn supports(height: usize, width: usize) -> bool {
        width.is_multiple_of(2) && width >= 4 && height >= 2
    }

    /// Hierarchy for the operator with these edges and f64 diagonal (the Poisson system's).
    pub(super) fn build(
        height: usize,
        width: usize,
        right: &[f32],
        down: &[f32],
        diag: &[f64],
    ) -> Self {
        let n = height * width;
        let mut fine_inv_diag = vec![0.0f32; n];
        // Mass = diagonal minus the incident edges, taken in f64 (it is small, λ, next to them)
        // and kept in f32 like the rest of the hierarchy.
        let mut mass = vec![0.0f32; n];
        fine_inv_diag
            .par_chunks_mut(width)
            .zip(mass.par_chunks_mut(width))
            .enumerate()
            .for_each(|(i, (inv, mass))| {
                let base = i * width;
                for j in 0..width {
                    let p = base + j;
                    let left = if j == 0 { p + width - 1 } else { p - 1 };
                    let mut edges =
                        f64::from(right[p]) + f64::from(right[left]) + f64::from(down[p]);
                    if i > 0 {
                        edges += f64::from(down[p - width]);
                    }
                    inv[j] = (1.0 / diag[p]) as f32;
                    mass[j] = (diag[p] - edges).max(0.0) as f32;
                }
            });
        let mut coarse: Vec<Coarse> = Vec::new();
        let (mut h, mut w) = (height, width);
        let mut level_mass = mass;
        while coarsens(h, w) {
            let (fr, fd) = match coarse.last() {
                None => (right, down),
                Some(c) => (&c.grid.right[..], &c.grid.down[..]),
            };
            let (grid, m) = coarsen(h, w, fr, fd, &level_mass);
            h = grid.height;
            w = grid.width;
            level_mass = m;
            let nc = h * w;
            coarse.push(Coarse {
                grid,
                b: vec![0.0; nc],
                x: vec![0.0; nc],
            });
        }
        Self {
            height,
            width,
            fine_inv_diag,
            coarse,
        }
    }

    /// Number of grids, the finest included.
    #[cfg(test)]
    pub(super) fn levels(&self) -> usize {
        self.coarse.len() + 1
    }

    /// z = V-cycle applied to r on the finest grid (whose edges are `right`, `down`); returns
    /// r·z summed over fixed chunks in order.
    pub(super) fn apply(&mut self, right: &[f32], down: &[f32], r: &[f64], z: &mut [f32]) -> f64 {
        let op = Op {
            height: self.height,
            width: self.width,
            right,
            down,
            inv_diag: &self.fine_inv_diag,
        };
        v_cycle(op, r, z, &mut self.coarse)
    }
}

/// 2×2 aggregation of an H×W grid (H even, W a multiple of 4): the coarse grid and its mass.
fn coarsen(h: usize, w: usize, right: &[f32], down: &[f32], mass: &[f32]) -> (Grid, Vec<f32>) {
    let (hc, wc) = (h / 2, w / 2);
    let nc = hc * wc;
    let (mut cr, mut cd, mut cm) = (vec![0.0f32; nc], vec![0.0f32; nc], vec![0.0f32; nc]);
    cr.par_chunks_mut(wc)
        .zip(cd.par_chunks_mut(wc))
        .zip(cm.par_chunks_mut(wc))
        .enumerate()
        .for_each(|(ic, ((cr, cd), cm))| {
            let (i0, i1) = (2 * ic, 2 * ic + 1);
            for jc in 0..wc {
                let (j0, j1) = (2 * jc, 2 * jc + 1);
                // Edges leaving the aggregate to the right: from column j1 on both rows.
                cr[jc] = COARSE_EDGE_SCALE * (right[i0 * w + j1] + right[i1 * w + j1]);
                // Down: from row i1 on both columns (0 on the last row already).
                cd[jc] = COARSE_EDGE_SCALE * (down[i1 * w + j0] + down[i1 * w + j1]);
                cm[jc] =
                    mass[i0 * w + j0] + mass[i0 * w + j1] + mass[i1 * w + j0] + mass[i1 * w + j1];
            }
        });
    let mut inv_diag = vec![0.0f32; nc];
    inv_diag
        .par_chunks_mut(wc)
        .enumerate()
        .for_each(|(i, inv)| {
            for (j, v) in inv.iter_mut().enumerate() {
                let p = i * wc + j;
                let left = if j == 0 { p + wc - 1 } else { p - 1 };
                let mut d =
                    f64::from(cm[p]) + f64::from(cr[p]) + f64::from(cr[left]) + f64::from(cd[p]);
                if i > 0 {
                    d += f64::from(cd[p - wc]);
                }
                *v = (1.0 / d) as f32;
            }
        });
    (
        Grid {
            height: hc,
            width: wc,
            right: cr,
            down: cd,
            inv_diag,
        },
        cm,
    )
}

/// `out[j]` = Σ over the four neighbours of pixel (i, j) of edge weight × value, for a whole
/// row i: `mid` holds the row's values, `above`/`below` the neighbouring rows' (None at a pole),
/// `right`/`down` the row's edges and `up` the edges of the row above. Whole rows of plain
/// slices so the loops vectorise; the colour a caller needs is picked afterwards.
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
#[inline(always)]
fn row_sum(
    out: &mut [f32],
    right: &[f32],
    mid: &[f32],
    below: Neighbour<'_>,
    above: Neighbour<'_>,
) {
    let w = mid.len();
    debug_assert!(w >= 2 && out.len() == w && right.len() == w);
    out[0] = right[0] * mid[1] + right[w - 1] * mid[w - 1];
    for (((o, r), rl), (vl, vr)) in out[1..w - 1]
        .iter_mut()
        .zip(&right[1..w - 1])
        .zip(&right[..w - 2])
        .zip(mid[..w - 2].iter().zip(&mid[2..]))
    {
        *o = r * vr + rl * vl;
    }
    out[w - 1] = right[w - 1] * mid[0] + right[w - 2] * mid[w - 2];
    for (edges, values) in [below, above].into_iter().flatten() {
        for ((o, e), v) in out.iter_mut().zip(edges).zip(values) {
            *o += e * v;
        }
    }
}

/// A neighbouring row's edges and values (None across a pole), for [`row_sum`].
type Neighbour<'a> = Option<(&'a [f32], &'a [f32])>;

/// Rows `i + 1` and `i − 1` of a grid-sized vector with the vertical edges to them.
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
#[inline(always)]
fn vertical<'a>(op: &Op<'a>, v: &'a [f32], i: usize) -> (Neighbour<'a>, Neighbour<'a>) {
    let (h, w) = (op.height, op.width);
    let row = |k: usize| k * w..(k + 1) * w;
    let below = (i + 1 < h).then(|| (&op.down[row(i)], &v[row(i + 1)]));
    let above = (i > 0).then(|| (&op.down[row(i - 1)], &v[row(i - 1)]));
    (below, above)
}

/// Computed rows i − 1, i, i + 1 of a vector that exists only row by row (`fill(i, row)`).
struct RowWindow {
    rows: [Vec<f32>; 3],
    /// Row held in `rows[1]`.
    at: usize,
}

impl RowWindow {
    fn new(width: usize) -> Self {
        Self {
            rows: [vec![0.0; width], vec![0.0; width], vec![0.0; width]],
            at: usize::MAX,
        }
    }

    /// Moves the window to centre row `i` (rows outside 0..height are left stale: callers do
    /// not read them).
    fn centre(&mut self, i: usize, height: usize, fill: &mut impl FnMut(usize, &mut [f32])) {
        if self.at.checked_add(1) == Some(i) {
            self.rows.rotate_left(1);
        } else {
            if i > 0 {
                fill(i - 1, &mut self.rows[0]);
            }
            fill(i, &mut self.rows[1]);
        }
        if i + 1 < height {
            fill(i + 1, &mut self.rows[2]);
        }
        self.at = i;
    }

    fn sum(&self, op: &Op<'_>, i: usize, out: &mut [f32]) {
        let (h, w) = (op.height, op.width);
        let row = |k: usize| k * w..(k + 1) * w;
        let below = (i + 1 < h).then(|| (&op.down[row(i)], &self.rows[2][..]));
        let above = (i > 0).then(|| (&op.down[row(i - 1)], &self.rows[0][..]));
        row_sum(out, &op.right[row(i)], &self.rows[1], below, above);
    }
}

/// `out` = (b + s) / d for a row: the Gauss–Seidel value given the neighbour sum `s`.
#[expect(
    clippy::inline_always,
    reason = "per-pixel kernel; inlined it measured faster"
)]
#[inline(always)]
fn relax<B: Rhs>(out: &mut [f32], b: &[B], s: &[f32], inv_diag: &[f32]) {
    for (((o, b), s), d) in out.iter_mut().zip(b).zip(s).zip(inv_diag) {
        *o = (b.get() + s) * d;
    }
}

/// One V-cycle from zero on the grid `op` with right-hand side `b`: writes `z` and returns
/// b·z (fixed-order partial sums). `coarse` holds the grids below.
///
/// Two passes over the grid: the black values of either black half sweep exist only in a
/// window of three rows (recomputed for the two halo rows of each work item), so the level's
/// memory traffic is reading b, 1/d and the edges twice and writing z once.
fn v_cycle<B: Rhs>(op: Op<'_>, b: &[B], z: &mut [f32], coarse: &mut [Coarse]) -> f64 {
    let Some((next, below)) = coarse.split_first_mut() else {
        return jacobi_solve(op, b, z);
    };
    let (h, w) = (op.height, op.width);
    let row = |k: usize| k * w..(k + 1) * w;
    // The red values after the first half sweep from zero: b / d.
    let red0 = |i: usize, out: &mut [f32]| {
        for ((o, b), d) in out.iter_mut().zip(&b[row(i)]).zip(&op.inv_diag[row(i)]) {
            *o = b.get() * d;
        }
    };
    // A black half sweep's row i given the red values `red` (computed at every pixel; only
    // the black ones are read).
    let black_row = |red: &mut RowWindow,
                     fill_red: &mut dyn FnMut(usize, &mut [f32]),
                     s: &mut [f32],
                     i: usize,
                     out: &mut [f32]| {
        red.centre(i, h, &mut |k, o| fill_red(k, o));
        red.sum(&op, i, s);
        relax(out, &b[row(i)], s, &op.inv_diag[row(i)]);
    };
    // (1) Residuals after red then black: 0 at black pixels (just solved), Σ edge·black at red
    // ones (their own b − d·x is 0); summed over each 2×2 aggregate, which holds one red pixel
    // per row.
    let wc = next.grid.width;
    next.b
        .par_chunks_mut(ROWS * wc)
        .enumerate()
        .for_each(|(c, cb)| {
            let (mut red, mut black) = (RowWindow::new(w), RowWindow::new(w));
            let (mut s, mut t) = (vec![0.0f32; w], vec![0.0f32; w]);
            let mut fill_red = |k: usize, o: &mut [f32]| red0(k, o);
            for (r, cb) in cb.chunks_mut(wc).enumerate() {
                let (i0, i1) = (2 * (c * ROWS + r), 2 * (c * ROWS + r) + 1);
                let mut fill_black =
                    |k: usize, o: &mut [f32]| black_row(&mut red, &mut fill_red, &mut t, k, o);
                black.centre(i0, h, &mut fill_black);
                black.sum(&op, i0, &mut s);
                // Row i0 is even: red at even columns; row i1 at odd ones.
                for (v, a) in cb.iter_mut().zip(s.chunks_exact(2)) {
                    *v = a[0];
                }
                black.centre(i1, h, &mut fill_black);
                black.sum(&op, i1, &mut s);
                for (v, a) in cb.iter_mut().zip(s.chunks_exact(2)) {
                    *v += a[1];
                }
            }
        });
    v_cycle(next.grid.op(), &next.b, &mut next.x, below);
    let correction = &next.x;
    // (2) Black after the prolonged correction (red values b / d + e), then red; z takes both
    // colours, and b·z is summed on the way.
    let red1 = |i: usize, out: &mut [f32]| {
        red0(i, out);
        let e = &correction[(i / 2) * wc..(i / 2 + 1) * wc];
        for (o, e) in out.chunks_exact_mut(2).zip(e) {
            o[0] += e;
            o[1] += e;
        }
    };
    let parts: Vec<f64> = z
        .par_chunks_mut(2 * ROWS * w)
        .enumerate()
        .map(|(c, out)| {
            let (mut red, mut black) = (RowWindow::new(w), RowWindow::new(w));
            let (mut s, mut t) = (vec![0.0f32; w], vec![0.0f32; w]);
            let mut fill_red = |k: usize, o: &mut [f32]| red1(k, o);
            let mut dot = 0.0f64;
            for (r, out) in out.chunks_mut(w).enumerate() {
                let i = c * 2 * ROWS + r;
                black.centre(i, h, &mut |k, o| {
                    black_row(&mut red, &mut fill_red, &mut t, k, o);
                });
                black.sum(&op, i, &mut s);
                relax(out, &b[row(i)], &s, &op.inv_diag[row(i)]);
                let first_black = 1 - i % 2;
                for (o, v) in out[first_black..]
                    .iter_mut()
                    .step_by(2)
                    .zip(black.rows[1][first_black..].iter().step_by(2))
                {
                    *o = *v;
                }
                dot += out
                    .iter()
                    .zip(&b[row(i)])
                    .map(|(z, b)| f64::from(*z) * f64::from(b.get()))
                    .sum::<f64>();
            }
            dot
        })
        .collect();
    parts.iter().sum()
}

/// Damped Jacobi sweeps from zero on the coarsest grid (a fixed polynomial in D⁻¹A: symmetric,
/// and positive for ω < 1). `tmp` is scratch.
fn jacobi_solve<B: Rhs>(op: Op<'_>, b: &[B], z: &mut [f32]) -> f64 {
    let w = op.width;
    let mut tmp = vec![0.0f32; z.len()];
    let row = |k: usize| k * w..(k + 1) * w;
    z.par_iter_mut()
        .zip(b.par_iter())
        .zip(op.inv_diag.par_iter())
        .for_each(|((z, b), d)| *z = COARSE_OMEGA * b.get() * d);
    for _ in 1..COARSE_SWEEPS {
        {
            let x = &*z;
            tmp.par_chunks_mut(w).enumerate().for_each(|(i, out)| {
                let mut s = vec![0.0f32; w];
                let (dn, up) = vertical(&op, x, i);
                row_sum(&mut s, &op.right[row(i)], &x[row(i)], dn, up);
                relax(out, &b[row(i)], &s, &op.inv_diag[row(i)]);
                for (o, x) in out.iter_mut().zip(&x[row(i)]) {
                    *o = (1.0 - COARSE_OMEGA) * x + COARSE_OMEGA * *o;
                }
            });
        }
        z.copy_from_slice(&tmp);
    }
    let parts: Vec<f64> = z
        .par_chunks(w)
        .zip(b.par_chunks(w))
        .map(|(z, b)| {
            z.iter()
                .zip(b)
                .map(|(&z, b)| f64::from(z) * f64::from(b.get()))
                .sum()
        })
        .collect();
    parts.iter().sum()
}
