//! Conjugate-gradient solvers of the Poisson system: multigrid-preconditioned (the default),
//! fused Jacobi-preconditioned, and faer's with the Jacobi preconditioner.

use super::system::System;
use super::{PoissonParams, PoissonSolver};
use crate::blend::multigrid::Multigrid;
use crate::error::{CoreError, Result};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::matrix_free::conjugate_gradient::{
    conjugate_gradient, conjugate_gradient_scratch, CgError, CgParams,
};
use faer::matrix_free::{InitialGuessStatus, LinOp, Precond};
use faer::{MatMut, MatRef, Par};
use rayon::prelude::*;
use std::sync::{Mutex, PoisonError};

/// Copy of column 0 of `m` as a contiguous slice (borrowed when it already is one).
fn column(m: MatRef<'_, f64>) -> std::borrow::Cow<'_, [f64]> {
    match m.col(0).try_as_col_major() {
        Some(c) => std::borrow::Cow::Borrowed(c.as_slice()),
        None => std::borrow::Cow::Owned(m.col(0).iter().copied().collect()),
    }
}

fn write_column(mut out: MatMut<'_, f64>, f: impl FnOnce(&mut [f64])) {
    if let Some(c) = out.as_mut().col_mut(0).try_as_col_major_mut() {
        f(c.as_slice_mut());
    } else {
        let mut tmp = vec![0.0; out.nrows()];
        f(&mut tmp);
        for (i, v) in tmp.into_iter().enumerate() {
            out[(i, 0)] = v;
        }
    }
}

/// The system matrix as a faer operator, applied matrix-free (5 non-zeros per row are never
/// stored: 4 bytes of weight per edge instead of ~60 bytes of CSR per pixel).
impl LinOp<f64> for System {
    fn apply_scratch(&self, _rhs_ncols: usize, _par: Par) -> faer::dyn_stack::StackReq {
        faer::dyn_stack::StackReq::EMPTY
    }
    fn nrows(&self) -> usize {
        self.diag.len()
    }
    fn ncols(&self) -> usize {
        self.diag.len()
    }
    fn apply(&self, out: MatMut<'_, f64>, rhs: MatRef<'_, f64>, _par: Par, _: &mut MemStack) {
        debug_assert_eq!(rhs.ncols(), 1);
        let x = column(rhs);
        write_column(out, |y| System::apply(self, &x, y));
    }
    fn conj_apply(&self, out: MatMut<'_, f64>, rhs: MatRef<'_, f64>, par: Par, s: &mut MemStack) {
        LinOp::apply(self, out, rhs, par, s);
    }
}

/// A symmetric positive definite approximation of A⁻¹ applied to one vector: z = M r.
trait Preconditioner: Sync + std::fmt::Debug {
    fn len(&self) -> usize;
    fn precondition(&self, r: &[f64], z: &mut [f64]);
}

/// A [`Preconditioner`] as faer's operator and `Precond`.
#[derive(Debug)]
struct ForFaer<P>(P);

impl<P: Preconditioner> LinOp<f64> for ForFaer<P> {
    fn apply_scratch(&self, _rhs_ncols: usize, _par: Par) -> faer::dyn_stack::StackReq {
        faer::dyn_stack::StackReq::EMPTY
    }
    fn nrows(&self) -> usize {
        self.0.len()
    }
    fn ncols(&self) -> usize {
        self.0.len()
    }
    fn apply(&self, out: MatMut<'_, f64>, rhs: MatRef<'_, f64>, _par: Par, _: &mut MemStack) {
        let r = column(rhs);
        write_column(out, |z| self.0.precondition(&r, z));
    }
    fn conj_apply(&self, out: MatMut<'_, f64>, rhs: MatRef<'_, f64>, par: Par, s: &mut MemStack) {
        LinOp::apply(self, out, rhs, par, s);
    }
}

impl<P: Preconditioner> Precond<f64> for ForFaer<P> {
    fn apply_in_place_scratch(&self, _rhs_ncols: usize, _par: Par) -> faer::dyn_stack::StackReq {
        faer::dyn_stack::StackReq::EMPTY
    }
    fn apply_in_place(&self, rhs: MatMut<'_, f64>, _par: Par, _: &mut MemStack) {
        write_column(rhs, |y| {
            let r = y.to_vec();
            self.0.precondition(&r, y);
        });
    }
    fn conj_apply_in_place(&self, rhs: MatMut<'_, f64>, par: Par, s: &mut MemStack) {
        self.apply_in_place(rhs, par, s);
    }
}

/// Jacobi (diagonal) preconditioner: with λ = 0.1 the system is well conditioned, and scaling
/// by the diagonal evens out the 1–5-fold overlap of the faces.
#[derive(Debug)]
struct Jacobi<'a>(&'a [f64]);

impl Preconditioner for Jacobi<'_> {
    fn len(&self) -> usize {
        self.0.len()
    }
    fn precondition(&self, r: &[f64], z: &mut [f64]) {
        z.par_chunks_mut(1 << 14)
            .zip(r.par_chunks(1 << 14))
            .zip(self.0.par_chunks(1 << 14))
            .for_each(|((z, r), d)| {
                for ((z, r), d) in z.iter_mut().zip(r).zip(d) {
                    *z = r / d;
                }
            });
    }
}

/// The multigrid V-cycle (see [`Multigrid`]). faer's `Precond` takes `&self` while a V-cycle
/// reuses its coarse-grid buffers, hence the locks (never contended: CG applies the
/// preconditioner from one thread at a time).
#[derive(Debug)]
struct VCycle<'a> {
    multigrid: Mutex<Multigrid>,
    z: Mutex<Vec<f32>>,
    system: &'a System,
}

impl Preconditioner for VCycle<'_> {
    fn len(&self) -> usize {
        self.system.diag.len()
    }
    fn precondition(&self, r: &[f64], out: &mut [f64]) {
        let mut mg = self
            .multigrid
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let mut z = self.z.lock().unwrap_or_else(PoisonError::into_inner);
        mg.apply(&self.system.right, &self.system.down, r, &mut z);
        out.par_iter_mut()
            .zip(z.par_iter())
            .for_each(|(o, &z)| *o = f64::from(z));
    }
}

/// Solve the system with faer's `conjugate_gradient`, preconditioned by the multigrid V-cycle
/// (Jacobi where the grid does not support it), warm-started from `x`.
///
/// faer's own vector operations run with `Par::Seq`: its parallel dot products split by thread
/// count, which would make the result depend on it; the operator and the preconditioner (most
/// of the work) run on the rayon pool with per-element writes, so the solve is bit-identical for
/// any number of threads. faer's recursive residual drifts from the true one, so the true
/// relative residual is recomputed and the solve restarted from its own result while it is above
/// the tolerance.
pub(crate) fn solve_faer(
    system: &System,
    x: &mut [f64],
    params: &PoissonParams,
) -> Result<(usize, f64, f64)> {
    let (h, w) = (system.height, system.width);
    if Multigrid::supports(h, w) {
        let precond = VCycle {
            multigrid: Mutex::new(Multigrid::build(
                h,
                w,
                &system.right,
                &system.down,
                &system.diag,
            )),
            z: Mutex::new(vec![0.0; h * w]),
            system,
        };
        faer_cg(system, &ForFaer(precond), x, params)
    } else {
        faer_cg(system, &ForFaer(Jacobi(&system.diag)), x, params)
    }
}

fn faer_cg(
    system: &System,
    precond: &impl Precond<f64>,
    x: &mut [f64],
    params: &PoissonParams,
) -> Result<(usize, f64, f64)> {
    let n = x.len();
    let par = Par::Seq;
    let initial = system.relative_residual(x);
    let mut residual = initial;
    let mut iterations = 0usize;
    let mut buffer = MemBuffer::new(conjugate_gradient_scratch(precond, system, 1, par));
    // At most a few restarts: each one starts from a residual CG has already reduced.
    for _ in 0..8 {
        if residual <= params.tolerance || iterations >= params.iterations {
            break;
        }
        let cg = CgParams {
            initial_guess: InitialGuessStatus::MaybeNonZero,
            // Aim a little below the target so the true residual usually passes first time.
            rel_tolerance: params.tolerance * 0.5,
            max_iters: params.iterations - iterations,
            ..Default::default()
        };
        let stack = MemStack::new(&mut buffer);
        let out = MatMut::from_column_major_slice_mut(x, n, 1);
        let rhs = MatRef::from_column_major_slice(&system.rhs, n, 1);
        match conjugate_gradient(out, precond, system, rhs, cg, |_| {}, par, stack) {
            Ok(info) => iterations += info.iter_count.max(1),
            Err(CgError::NoConvergence { .. }) => iterations = params.iterations,
            Err(e) => {
                return Err(CoreError::NotPositiveDefinite {
                    what: "the Poisson system",
                    detail: format!("faer's conjugate gradient reported {e:?}"),
                })
            }
        }
        residual = system.relative_residual(x);
    }
    finish(residual, iterations, initial, params)
}

/// Rows per work item of the fused CG passes; partial sums are kept per item and added in item
/// order, so the reductions do not depend on the number of threads.
pub(crate) const CG_ROWS: usize = 8;

/// Jacobi-preconditioned CG written as three fused sweeps per iteration:
/// 1. `Ap = A p` and the partial sums of `pᵀAp`;
/// 2. `x += α p`, `r −= α Ap`, and the partial sums of `rᵀz` (z = r / diag) and `rᵀr`;
/// 3. `p = z + β p`.
///
/// faer's CG makes about seven separate passes over the vectors per iteration; on this
/// memory-bound problem the fused form measured about twice as fast. The stopping test uses the
/// recursive residual; the true residual is recomputed afterwards and the solve restarted from
/// its own result if that drifted above the tolerance.
pub(crate) fn solve_fused(
    system: &System,
    x: &mut [f64],
    params: &PoissonParams,
) -> Result<(usize, f64, f64)> {
    let n = x.len();
    let w = system.width;
    let chunk = CG_ROWS * w;
    // The preconditioner as a product: two divisions per pixel per iteration cost as much as
    // the memory traffic of a whole sweep.
    let inv_diag: Vec<f64> = system.diag.par_iter().map(|d| 1.0 / d).collect();
    let diag = &inv_diag;
    let b = &system.rhs;
    let b_norm = ordered_sum(b.par_chunks(chunk).map(|c| c.iter().map(|v| v * v).sum())).sqrt();
    let initial = system.relative_residual(x);
    if b_norm == 0.0 {
        x.fill(0.0);
        return Ok((0, 0.0, initial));
    }
    let mut r = vec![0.0f64; n];
    let mut p = vec![0.0f64; n];
    let mut ap = vec![0.0f64; n];
    let mut iterations = 0usize;
    let mut residual = initial;
    for _ in 0..8 {
        if residual <= params.tolerance || iterations >= params.iterations {
            break;
        }
        // r = b − A x, p = z = r / diag.
        system.apply(x, &mut r);
        let mut rz = ordered_sum(
            r.par_chunks_mut(chunk)
                .zip(p.par_chunks_mut(chunk))
                .zip(b.par_chunks(chunk))
                .zip(diag.par_chunks(chunk))
                .map(|(((r, p), b), d)| {
                    let mut s = 0.0;
                    for (((r, p), b), d) in r.iter_mut().zip(p.iter_mut()).zip(b).zip(d) {
                        *r = b - *r;
                        *p = *r * d;
                        s += *r * *p;
                    }
                    s
                }),
        );
        // A little below the target: the recursive residual drifts slightly from the true one.
        let threshold = 0.8 * params.tolerance * b_norm;
        while iterations < params.iterations {
            let pap = ordered_sum(
                ap.par_chunks_mut(chunk)
                    .enumerate()
                    .map(|(c, ap)| system.apply_rows(&p, ap, c * CG_ROWS)),
            );
            if !(pap > 0.0 && pap.is_finite()) {
                return Err(CoreError::NotPositiveDefinite {
                    what: "the Poisson system",
                    detail: format!("pᵀAp = {pap:e}"),
                });
            }
            let alpha = rz / pap;
            let (rz_new, rr) = ordered_sum2(
                x.par_chunks_mut(chunk)
                    .zip(r.par_chunks_mut(chunk))
                    .zip(p.par_chunks(chunk))
                    .zip(ap.par_chunks(chunk))
                    .zip(diag.par_chunks(chunk))
                    .map(|((((x, r), p), ap), d)| {
                        let (mut rz, mut rr) = (0.0, 0.0);
                        for ((((x, r), p), ap), d) in
                            x.iter_mut().zip(r.iter_mut()).zip(p).zip(ap).zip(d)
                        {
                            *x += alpha * p;
                            *r -= alpha * ap;
                            let r2 = *r * *r;
                            rz += r2 * d;
                            rr += r2;
                        }
                        (rz, rr)
                    }),
            );
            iterations += 1;
            if rr.sqrt() <= threshold {
                break;
            }
            let beta = rz_new / rz;
            rz = rz_new;
            p.par_chunks_mut(chunk)
                .zip(r.par_chunks(chunk))
                .zip(diag.par_chunks(chunk))
                .for_each(|((p, r), d)| {
                    for ((p, r), d) in p.iter_mut().zip(r).zip(d) {
                        *p = r * d + beta * *p;
                    }
                });
        }
        residual = system.relative_residual(x);
    }
    finish(residual, iterations, initial, params)
}

/// Sum of per-chunk partial sums in chunk order (deterministic for any thread count).
pub(crate) fn ordered_sum(parts: impl IndexedParallelIterator<Item = f64>) -> f64 {
    parts.collect::<Vec<f64>>().iter().sum()
}

pub(crate) fn ordered_sum2(parts: impl IndexedParallelIterator<Item = (f64, f64)>) -> (f64, f64) {
    parts
        .collect::<Vec<(f64, f64)>>()
        .iter()
        .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1))
}

fn finish(
    residual: f64,
    iterations: usize,
    initial: f64,
    params: &PoissonParams,
) -> Result<(usize, f64, f64)> {
    if !(residual.is_finite() && residual <= params.tolerance) {
        if !residual.is_finite() {
            return Err(CoreError::NonFinite {
                what: "Poisson residual",
            });
        }
        return Err(CoreError::NotConverged {
            what: "the Poisson blend",
            iterations,
            residual,
            tolerance: params.tolerance,
        });
    }
    Ok((iterations, residual, initial))
}

/// CG preconditioned by one multigrid V-cycle per iteration (see [`multigrid`]), with the
/// same fused f64 passes and restarts as [`solve_fused`]; z = M r is kept in f32.
pub(crate) fn solve_multigrid(
    system: &System,
    x: &mut [f64],
    params: &PoissonParams,
) -> Result<(usize, f64, f64)> {
    let (h, w) = (system.height, system.width);
    if !Multigrid::supports(h, w) {
        return solve_fused(system, x, params);
    }
    let n = x.len();
    let chunk = CG_ROWS * w;
    let b = &system.rhs;
    let b_norm = ordered_sum(b.par_chunks(chunk).map(|c| c.iter().map(|v| v * v).sum())).sqrt();
    let initial = system.relative_residual(x);
    if b_norm == 0.0 {
        x.fill(0.0);
        return Ok((0, 0.0, initial));
    }
    let mut mg = Multigrid::build(h, w, &system.right, &system.down, &system.diag);
    let (right, down) = (&system.right[..], &system.down[..]);
    let mut r = vec![0.0f64; n];
    let mut p = vec![0.0f64; n];
    let mut ap = vec![0.0f64; n];
    let mut z = vec![0.0f32; n];
    let mut iterations = 0usize;
    let mut residual = initial;
    for _ in 0..8 {
        if residual <= params.tolerance || iterations >= params.iterations {
            break;
        }
        system.apply(x, &mut r);
        r.par_chunks_mut(chunk)
            .zip(b.par_chunks(chunk))
            .for_each(|(r, b)| r.iter_mut().zip(b).for_each(|(r, b)| *r = b - *r));
        let mut rz = mg.apply(right, down, &r, &mut z);
        p.par_iter_mut()
            .zip(z.par_iter())
            .for_each(|(p, &z)| *p = f64::from(z));
        let threshold = 0.8 * params.tolerance * b_norm;
        while iterations < params.iterations {
            let pap = ordered_sum(
                ap.par_chunks_mut(chunk)
                    .enumerate()
                    .map(|(c, ap)| system.apply_rows(&p, ap, c * CG_ROWS)),
            );
            if !(pap > 0.0 && pap.is_finite() && rz > 0.0) {
                return Err(CoreError::NotPositiveDefinite {
                    what: "the preconditioned Poisson system",
                    detail: format!("pᵀAp = {pap:e}, rᵀz = {rz:e}"),
                });
            }
            let alpha = rz / pap;
            let rr = ordered_sum(
                x.par_chunks_mut(chunk)
                    .zip(r.par_chunks_mut(chunk))
                    .zip(p.par_chunks(chunk))
                    .zip(ap.par_chunks(chunk))
                    .map(|(((x, r), p), ap)| {
                        let mut rr = 0.0;
                        for (((x, r), p), ap) in x.iter_mut().zip(r.iter_mut()).zip(p).zip(ap) {
                            *x += alpha * p;
                            *r -= alpha * ap;
                            rr += *r * *r;
                        }
                        rr
                    }),
            );
            iterations += 1;
            if rr.sqrt() <= threshold {
                break;
            }
            let rz_new = mg.apply(right, down, &r, &mut z);
            let beta = rz_new / rz;
            rz = rz_new;
            p.par_chunks_mut(chunk)
                .zip(z.par_chunks(chunk))
                .for_each(|(p, z)| {
                    for (p, &z) in p.iter_mut().zip(z) {
                        *p = f64::from(z) + beta * *p;
                    }
                });
        }
        residual = system.relative_residual(x);
    }
    finish(residual, iterations, initial, params)
}

pub(super) fn solve(
    system: &System,
    x: &mut [f64],
    params: &PoissonParams,
) -> Result<(usize, f64, f64)> {
    match params.solver {
        PoissonSolver::Multigrid => solve_multigrid(system, x, params),
        PoissonSolver::Fused => solve_fused(system, x, params),
        PoissonSolver::Faer => solve_faer(system, x, params),
    }
}
