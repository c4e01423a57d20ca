//! How much of the true wrinkle activations each conditioning signal explains.
//!
//! The point of eta (method §1) is that the same expression coefficients come with or
//! without muscle activation, and an image-derived code tells them apart. This module
//! measures it on an export: plain ridge regression of the true activations
//! (`truth/TTTTT.npz`, `activations`) on
//!
//! - the tracked expression coefficients and their squares (`flame_param/`, what training
//!   reads),
//! - the true expression coefficients and their squares (`truth/`; the part of the gap that
//!   tracking noise does not explain is the hidden tension),
//! - eta (`eta/`),
//!
//! cross-validated over all timesteps ([`cross_validated_r2`]: k folds, the ridge penalty
//! chosen per activation by an inner k-fold on each training part). The figure is R^2 of
//! the out-of-fold predictions per activation, averaged over the activations that vary.
//! It also reports the tracking error of the export: the distance between the meshes of
//! the true and the tracked parameters.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::data::vhap::eta_path;
use crate::error::{Error, Result};
use crate::head::{HeadAsset, HeadPose};
use crate::io::npz::Npz;
use crate::synth::appearance::{WRINKLE_NAMES, WRINKLES};
use crate::synth::{TRUTH_DIR, tracking};
use crate::util::rng::Pcg;

/// Folds of the outer cross-validation.
pub const FOLDS: usize = 5;
/// Random fold assignments the R^2 is averaged over (one assignment alone moves it by a
/// few hundredths).
pub const REPEATS: usize = 4;
/// Ridge penalties tried, relative to the features' mean variance times the rows
/// (see [`cross_validated_r2`]), chosen by the inner cross-validation.
pub const LAMBDAS: [f64; 9] = [1e-5, 1e-4, 1e-3, 1e-2, 0.03, 0.1, 0.3, 1.0, 10.0];

/// Cross-validated R^2 of one feature set.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Explained {
    /// What the features are.
    pub features: String,
    /// Their number.
    pub dims: usize,
    /// R^2 per activation (`None` where the activation does not vary).
    pub per_activation: Vec<Option<f64>>,
    /// The mean over the activations that vary.
    pub mean: f64,
}

/// The analysis of an export.
#[derive(Clone, Debug, Serialize)]
pub struct Analysis {
    /// The export folder.
    pub data: PathBuf,
    /// Timesteps read.
    pub timesteps: usize,
    /// Names of the activations, in order.
    pub activations: Vec<String>,
    /// Standard deviation of each activation over the timesteps.
    pub activation_std: Vec<f64>,
    /// On the tracked expression coefficients and their squares.
    pub tracked_expression: Explained,
    /// On the true expression coefficients and their squares.
    pub true_expression: Explained,
    /// On eta.
    pub eta: Explained,
    /// Mean distance between the true and the tracked mesh over all vertices and
    /// timesteps, mm (`None` without the export's `head/head.npz`).
    pub tracking_error_mm: Option<f64>,
    /// The same over the face (the vertices expressions move), mm.
    pub tracking_error_face_mm: Option<f64>,
}

impl Analysis {
    /// A few lines for the terminal.
    pub fn text(&self) -> String {
        let mut s = format!(
            "{}: {} timesteps; cross-validated R^2 ({FOLDS}-fold over timesteps, mean of {REPEATS} fold assignments, ridge) of the true wrinkle activations:\n",
            self.data.display(),
            self.timesteps
        );
        for e in [&self.tracked_expression, &self.true_expression, &self.eta] {
            s.push_str(&format!(
                "  {:<48} {:>4} features  R^2 {:.3}  per activation [{}]\n",
                e.features,
                e.dims,
                e.mean,
                e.per_activation
                    .iter()
                    .map(|r| r.map_or("-".to_string(), |r| format!("{r:.2}")))
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        if let (Some(all), Some(face)) = (self.tracking_error_mm, self.tracking_error_face_mm) {
            s.push_str(&format!(
                "  tracking error (flame_param vs truth): mean vertex distance {all:.2} mm, {face:.2} mm on the face\n"
            ));
        }
        s
    }
}

/// Cholesky factorisation `A = L L^T` of the symmetric positive definite `n x n` matrix
/// `a` (row-major), in place in its lower triangle; false when it is not positive definite.
fn cholesky(a: &mut [f64], n: usize) -> bool {
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if d <= 0.0 || !d.is_finite() {
            return false;
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = s / d;
        }
    }
    true
}

/// Solves `L L^T x = b` in place, `l` from [`cholesky`].
fn cholesky_solve(a: &[f64], b: &mut [f64], n: usize) {
    for i in 0..n {
        let mut s = b[i];
        for k in 0..i {
            s -= a[i * n + k] * b[k];
        }
        b[i] = s / a[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in i + 1..n {
            s -= a[k * n + i] * b[k];
        }
        b[i] = s / a[i * n + i];
    }
}

/// Solves the symmetric positive definite system `a x = b` in place (`a` is overwritten);
/// false when `a` is not positive definite.
#[cfg(test)]
fn solve_spd(a: &mut [f64], b: &mut [f64], n: usize) -> bool {
    if !cholesky(a, n) {
        return false;
    }
    cholesky_solve(a, b, n);
    true
}

/// A ridge fit on the rows `train` of `x` (centred on their means) for every target column
/// of `y` and every relative penalty: predictions for the rows `test`, indexed
/// `[lambda][target][test row]`. A relative penalty `l` adds `l * trace(X^T X) / p` to the
/// diagonal (the features' mean variance times the rows), so the grid suits any feature
/// scale. Features are not divided by their deviations: one that is almost constant on the
/// training rows (an expression unit that only a few frames use) would otherwise blow up
/// on a test row that uses it.
fn ridge_predict(
    x: &[Vec<f64>],
    y: &[Vec<f64>],
    train: &[usize],
    test: &[usize],
    lambdas: &[f64],
) -> Vec<Vec<Vec<f64>>> {
    let p = x.first().map_or(0, Vec::len);
    let m = y.first().map_or(0, Vec::len);
    let nt = train.len().max(1) as f64;
    let mean: Vec<f64> = (0..p)
        .map(|j| train.iter().map(|&i| x[i][j]).sum::<f64>() / nt)
        .collect();
    let z = |i: usize| -> Vec<f64> { (0..p).map(|j| x[i][j] - mean[j]).collect() };
    let zt: Vec<Vec<f64>> = train.iter().map(|&i| z(i)).collect();
    let zs: Vec<Vec<f64>> = test.iter().map(|&i| z(i)).collect();
    let ymean: Vec<f64> = (0..m)
        .map(|k| train.iter().map(|&i| y[i][k]).sum::<f64>() / nt)
        .collect();
    let mut gram = vec![0.0f64; p * p];
    for r in &zt {
        for a in 0..p {
            if r[a] == 0.0 {
                continue;
            }
            for b in 0..p {
                gram[a * p + b] += r[a] * r[b];
            }
        }
    }
    let xty: Vec<Vec<f64>> = (0..m)
        .map(|k| {
            (0..p)
                .map(|a| {
                    zt.iter()
                        .zip(train)
                        .map(|(r, &i)| r[a] * (y[i][k] - ymean[k]))
                        .sum::<f64>()
                })
                .collect()
        })
        .collect();
    let trace = (0..p).map(|d| gram[d * p + d]).sum::<f64>() / p.max(1) as f64;
    let unit = if trace > 0.0 { trace } else { 1.0 };
    lambdas
        .iter()
        .map(|&lam| {
            let mut a = gram.clone();
            for d in 0..p {
                a[d * p + d] += lam * unit;
            }
            let ok = cholesky(&mut a, p);
            (0..m)
                .map(|k| {
                    let mut w = xty[k].clone();
                    if ok {
                        cholesky_solve(&a, &mut w, p);
                    } else {
                        w = vec![0.0; p];
                    }
                    zs.iter()
                        .map(|r| ymean[k] + r.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>())
                        .collect()
                })
                .collect()
        })
        .collect()
}

/// `folds` nearly equal folds of `0..n` after a fixed shuffle.
fn fold_of(n: usize, folds: usize, seed: u64) -> Vec<usize> {
    let mut order: Vec<usize> = (0..n).collect();
    let mut rng = Pcg::new(seed);
    for i in (1..n).rev() {
        let j = (rng.next_u32() as usize) % (i + 1);
        order.swap(i, j);
    }
    let mut fold = vec![0; n];
    for (k, &i) in order.iter().enumerate() {
        fold[i] = k % folds.max(1);
    }
    fold
}

/// Cross-validated R^2 of a ridge regression of each column of `y` on the rows of `x`
/// (`n` rows each; features centred on each training part, the penalty `l * trace(X^T X)
/// / p`): `folds` outer folds over the rows, `l` chosen per column from [`LAMBDAS`] by an
/// inner `folds - 1` fold cross-validation on the training part. R^2 = 1 - SSE / SST of the pooled
/// out-of-fold predictions, averaged over [`REPEATS`] random fold assignments; `None` for
/// a column that does not vary. Needs at least `folds` rows and 2 folds.
pub fn cross_validated_r2(
    x: &[Vec<f64>],
    y: &[Vec<f64>],
    folds: usize,
) -> Result<Vec<Option<f64>>> {
    let n = x.len();
    if y.len() != n || n < folds.max(2) || folds < 2 {
        return Err(Error::invalid(
            "analysis",
            "rows",
            format!(
                "{n} feature rows and {} target rows for {folds} folds",
                y.len()
            ),
        ));
    }
    let m = y[0].len();
    let mut r2 = vec![0.0f64; m];
    for repeat in 0..REPEATS {
        let pred = out_of_fold(x, y, folds, 0x0f01d + repeat as u64);
        for (k, r) in r2.iter_mut().enumerate() {
            let mean = y.iter().map(|r| r[k]).sum::<f64>() / n as f64;
            let sst = y.iter().map(|r| (r[k] - mean).powi(2)).sum::<f64>();
            let sse = (0..n).map(|i| (y[i][k] - pred[k][i]).powi(2)).sum::<f64>();
            *r += (1.0 - sse / sst.max(f64::MIN_POSITIVE)) / REPEATS as f64;
        }
    }
    Ok((0..m)
        .map(|k| {
            let mean = y.iter().map(|r| r[k]).sum::<f64>() / n as f64;
            let sst = y.iter().map(|r| (r[k] - mean).powi(2)).sum::<f64>();
            (sst > 1e-9 * n as f64).then_some(r2[k])
        })
        .collect())
}

/// Out-of-fold predictions `[target][row]` of one `folds`-fold split drawn with `seed`
/// (see [`cross_validated_r2`]).
fn out_of_fold(x: &[Vec<f64>], y: &[Vec<f64>], folds: usize, seed: u64) -> Vec<Vec<f64>> {
    let n = x.len();
    let m = y[0].len();
    let outer = fold_of(n, folds, seed);
    let mut pred = vec![vec![0.0f64; n]; m];
    for f in 0..folds {
        let train: Vec<usize> = (0..n).filter(|&i| outer[i] != f).collect();
        let test: Vec<usize> = (0..n).filter(|&i| outer[i] == f).collect();
        // Inner folds choose the penalty per target.
        let inner_k = (folds - 1).clamp(2, train.len().max(2));
        let inner = fold_of(train.len(), inner_k, 0x1a2e + f as u64);
        let mut sse = vec![vec![0.0f64; m]; LAMBDAS.len()];
        for g in 0..inner_k {
            let tr: Vec<usize> = (0..train.len())
                .filter(|&i| inner[i] != g)
                .map(|i| train[i])
                .collect();
            let te: Vec<usize> = (0..train.len())
                .filter(|&i| inner[i] == g)
                .map(|i| train[i])
                .collect();
            if tr.is_empty() || te.is_empty() {
                continue;
            }
            let p = ridge_predict(x, y, &tr, &te, &LAMBDAS);
            for (l, pl) in p.iter().enumerate() {
                for k in 0..m {
                    sse[l][k] += te
                        .iter()
                        .zip(&pl[k])
                        .map(|(&i, q)| (y[i][k] - q).powi(2))
                        .sum::<f64>();
                }
            }
        }
        let p = ridge_predict(x, y, &train, &test, &LAMBDAS);
        for k in 0..m {
            let best = (0..LAMBDAS.len())
                .min_by(|&a, &b| sse[a][k].total_cmp(&sse[b][k]))
                .unwrap_or(0);
            for (j, &i) in test.iter().enumerate() {
                pred[k][i] = p[best][k][j];
            }
        }
    }
    pred
}

/// [`cross_validated_r2`] of `x` with [`FOLDS`] folds, averaged.
fn explained(features: &str, x: &[Vec<f64>], y: &[Vec<f64>]) -> Result<Explained> {
    let per = cross_validated_r2(x, y, FOLDS)?;
    let some: Vec<f64> = per.iter().flatten().copied().collect();
    Ok(Explained {
        features: features.to_string(),
        dims: x.first().map_or(0, Vec::len),
        mean: some.iter().sum::<f64>() / some.len().max(1) as f64,
        per_activation: per,
    })
}

/// Coefficients and their squares.
fn with_squares(c: &[f32]) -> Vec<f64> {
    c.iter()
        .map(|&v| f64::from(v))
        .chain(c.iter().map(|&v| f64::from(v) * f64::from(v)))
        .collect()
}

/// One timestep of an export: true parameters and activations, tracked parameters, eta.
struct Row {
    truth: HeadPose,
    act: Vec<f32>,
    tracked: HeadPose,
    eta: Vec<f32>,
}

/// What the regressions of one timestep use.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    /// The true expression coefficients.
    pub truth_expr: Vec<f32>,
    /// The tracked (reported) expression coefficients.
    pub tracked_expr: Vec<f32>,
    /// Eta.
    pub eta: Vec<f32>,
    /// The true wrinkle activations.
    pub activations: Vec<f32>,
}

impl From<&crate::synth::Frame> for Sample {
    fn from(f: &crate::synth::Frame) -> Self {
        Sample {
            truth_expr: f.truth.expr.clone(),
            tracked_expr: f.reported.expr.clone(),
            eta: f.eta.clone(),
            activations: f.activations.to_vec(),
        }
    }
}

/// The three cross-validated regressions of the module docs on `samples` (at least
/// [`FOLDS`], all of the same sizes): on the tracked expression and squares, on the true
/// expression and squares, on eta.
pub fn explain(samples: &[Sample]) -> Result<[Explained; 3]> {
    let what = "analysis";
    let Some(first) = samples.first() else {
        return Err(Error::invalid(what, "samples", "none"));
    };
    let same = |f: &dyn Fn(&Sample) -> usize, field: &str| -> Result<()> {
        let d = f(first);
        match samples.iter().position(|r| f(r) != d) {
            Some(i) => Err(Error::invalid(
                what,
                field,
                format!(
                    "timestep {i} has {} values, the first has {d}",
                    f(&samples[i])
                ),
            )),
            None => Ok(()),
        }
    };
    same(&|r| r.tracked_expr.len(), "tracked expr")?;
    same(&|r| r.truth_expr.len(), "true expr")?;
    same(&|r| r.eta.len(), "eta")?;
    same(&|r| r.activations.len(), "activations")?;
    let y: Vec<Vec<f64>> = samples
        .iter()
        .map(|r| r.activations.iter().map(|&a| f64::from(a)).collect())
        .collect();
    let tracked: Vec<Vec<f64>> = samples
        .iter()
        .map(|r| with_squares(&r.tracked_expr))
        .collect();
    let truth: Vec<Vec<f64>> = samples
        .iter()
        .map(|r| with_squares(&r.truth_expr))
        .collect();
    let eta: Vec<Vec<f64>> = samples
        .iter()
        .map(|r| r.eta.iter().map(|&v| f64::from(v)).collect())
        .collect();
    Ok([
        explained("tracked expression + squares (flame_param/)", &tracked, &y)?,
        explained("true expression + squares (truth/)", &truth, &y)?,
        explained("eta (eta/)", &eta, &y)?,
    ])
}

/// Reads every timestep of the export in `data` (the folder `texavatars synth --out`
/// wrote): each sequence folder with a `truth/` folder, its `TTTTT.npz` files and the
/// `flame_param/` and `eta/` files of the same timesteps.
fn read_rows(data: &Path) -> Result<Vec<Row>> {
    let mut seqs: Vec<PathBuf> = std::fs::read_dir(data)
        .map_err(|e| Error::io(data, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join(TRUTH_DIR).is_dir())
        .collect();
    seqs.sort();
    let mut rows = Vec::new();
    for seq in seqs {
        let dir = seq.join(TRUTH_DIR);
        for truth in crate::io::files_with_extension(&dir, "npz")? {
            let what = truth.display().to_string();
            let name = truth.file_name().unwrap_or_default();
            let param = seq.join("flame_param").join(name);
            let act = Npz::open(&truth)?.floats("activations")?;
            if act.data.len() != WRINKLES {
                return Err(Error::invalid(
                    &what,
                    "activations",
                    format!("{} values, expected {WRINKLES}", act.data.len()),
                ));
            }
            let eta = crate::io::npy::read(&eta_path(&param))?;
            rows.push(Row {
                truth: HeadPose::load_npz(&truth)?,
                act: act.data,
                tracked: HeadPose::load_npz(&param)?,
                eta: eta.data,
            });
        }
    }
    Ok(rows)
}

/// Analyses the export in `data` (see the module docs). Needs at least [`FOLDS`]
/// timesteps with `truth/` files.
pub fn analyse(data: &Path) -> Result<Analysis> {
    let rows = read_rows(data)?;
    let what = data.display().to_string();
    if rows.len() < FOLDS {
        return Err(Error::invalid(
            &what,
            TRUTH_DIR,
            format!(
                "{} timesteps with truth/ files; the analysis needs at least {FOLDS} (exports written before truth/ existed cannot be analysed)",
                rows.len()
            ),
        ));
    }
    let samples: Vec<Sample> = rows
        .iter()
        .map(|r| Sample {
            truth_expr: r.truth.expr.clone(),
            tracked_expr: r.tracked.expr.clone(),
            eta: r.eta.clone(),
            activations: r.act.clone(),
        })
        .collect();
    let [tracked, truth, eta] =
        explain(&samples).map_err(|e| Error::invalid(&what, "analysis", e.to_string()))?;
    let y: Vec<Vec<f64>> = rows
        .iter()
        .map(|r| r.act.iter().map(|&a| f64::from(a)).collect())
        .collect();
    let n = rows.len() as f64;
    let activation_std = (0..WRINKLES)
        .map(|k| {
            let m = y.iter().map(|r| r[k]).sum::<f64>() / n;
            (y.iter().map(|r| (r[k] - m).powi(2)).sum::<f64>() / n).sqrt()
        })
        .collect();
    let head = data.join("head/head.npz");
    let (mut err_all, mut err_face) = (None, None);
    if head.is_file() {
        let model = HeadAsset::load(&head, None)?.model;
        let face = tracking::face_vertices(&model);
        let (mut a, mut f) = (0.0, 0.0);
        for r in &rows {
            a += tracking::vertex_error(&model, &r.truth, &r.tracked, &[])?.0;
            f += tracking::vertex_error(&model, &r.truth, &r.tracked, &face)?.0;
        }
        err_all = Some(a / n * 1e3);
        err_face = Some(f / n * 1e3);
    }
    Ok(Analysis {
        data: data.to_path_buf(),
        timesteps: rows.len(),
        activations: WRINKLE_NAMES.iter().map(|s| s.to_string()).collect(),
        activation_std,
        tracked_expression: tracked,
        true_expression: truth,
        eta,
        tracking_error_mm: err_all,
        tracking_error_face_mm: err_face,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ridge_cross_validation_tells_signal_from_noise() {
        let mut rng = Pcg::new(11);
        let n = 120;
        // Three features; target 0 is linear in them, target 1 half linear and half a
        // hidden variable, target 2 independent noise, target 3 constant.
        let x: Vec<Vec<f64>> = (0..n)
            .map(|_| (0..3).map(|_| f64::from(rng.normal())).collect())
            .collect();
        let y: Vec<Vec<f64>> = x
            .iter()
            .map(|r| {
                let hidden = f64::from(rng.normal());
                vec![
                    2.0 * r[0] - r[1] + 0.5 * r[2] + 0.05 * f64::from(rng.normal()),
                    r[0] + hidden,
                    f64::from(rng.normal()),
                    3.0,
                ]
            })
            .collect();
        let r2 = cross_validated_r2(&x, &y, 5).expect("cv");
        let r = |k: usize| r2[k].expect("varies");
        assert!(r(0) > 0.99, "{r2:?}");
        assert!(r(1) > 0.3 && r(1) < 0.7, "{r2:?}");
        assert!(r(2) < 0.1, "{r2:?}");
        assert_eq!(r2[3], None);
        // More features than rows (133 for 96 training rows): the penalty keeps it sane,
        // the signal still shows and noise explains nothing.
        let wide: Vec<Vec<f64>> = x
            .iter()
            .map(|r| {
                let mut w = r.clone();
                w.extend((0..130).map(|_| f64::from(rng.normal())));
                w
            })
            .collect();
        let r2w = cross_validated_r2(&wide, &y, 5).expect("cv");
        assert!(r2w[0].expect("varies") > 0.5, "{r2w:?}");
        assert!(r2w[2].expect("varies") < 0.15, "{r2w:?}");
        assert!(cross_validated_r2(&x[..3], &y[..3], 5).is_err());
    }

    #[test]
    fn cholesky_solves() {
        let mut a = vec![4.0, 2.0, 2.0, 3.0];
        let mut b = vec![2.0, 1.0];
        assert!(solve_spd(&mut a, &mut b, 2));
        assert!((b[0] - 0.5).abs() < 1e-12 && b[1].abs() < 1e-12, "{b:?}");
        let mut singular = vec![0.0; 4];
        assert!(!solve_spd(&mut singular, &mut [1.0, 1.0], 2));
    }
}
