//! Symmetric eigendecomposition for the small fixed-size matrices of the shard stage: the ground
//! plane's normal (3×3 covariance of the means, [`super::tiles`]) and the scene→map similarity
//! (Horn's 4×4 quaternion matrix and the 3×3 spread test, [`super::frame`]).

/// Eigenvalues and eigenvectors of a symmetric `N × N` matrix by cyclic Jacobi rotations: returns
/// `(w, v)` with `w[i]` the eigenvalues (unsorted) and column `i` of `v` (`v[r][i]`) the unit
/// eigenvector of `w[i]`. Stops when the off-diagonal mass is below `1e-32` of the matrix's
/// squared Frobenius norm, or after 100 sweeps. Only the upper triangle's symmetry is assumed,
/// not checked.
pub(crate) fn jacobi_eigen<const N: usize>(mut a: [[f64; N]; N]) -> ([f64; N], [[f64; N]; N]) {
    let mut v = [[0.0; N]; N];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    let scale: f64 = a.iter().flatten().map(|x| x * x).sum::<f64>().max(1e-300);
    for _ in 0..100 {
        let off: f64 = (0..N)
            .flat_map(|p| (p + 1..N).map(move |q| (p, q)))
            .map(|(p, q)| a[p][q] * a[p][q])
            .sum();
        if off <= 1e-32 * scale {
            break;
        }
        for (p, q) in (0..N).flat_map(|p| (p + 1..N).map(move |q| (p, q))) {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = if theta == 0.0 {
                1.0
            } else {
                theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt())
            };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for row in a.iter_mut() {
                let (akp, akq) = (row[p], row[q]);
                row[p] = c * akp - s * akq;
                row[q] = s * akp + c * akq;
            }
            let (rp, rq) = (a[p], a[q]);
            for k in 0..N {
                a[p][k] = c * rp[k] - s * rq[k];
                a[q][k] = s * rp[k] + c * rq[k];
            }
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    let mut w = [0.0; N];
    for (i, x) in w.iter_mut().enumerate() {
        *x = a[i][i];
    }
    (w, v)
}

#[cfg(test)]
mod tests {
    use super::jacobi_eigen;

    /// A·v_i = w_i·v_i and VᵀV = I for symmetric matrices of both sizes the shard stage uses,
    /// including repeated eigenvalues and a zero matrix.
    #[test]
    fn decomposes_symmetric_matrices() {
        fn check<const N: usize>(a: [[f64; N]; N]) {
            let (w, v) = jacobi_eigen(a);
            let norm: f64 = a
                .iter()
                .flatten()
                .map(|x| x * x)
                .sum::<f64>()
                .sqrt()
                .max(1.0);
            for i in 0..N {
                for r in 0..N {
                    let av: f64 = (0..N).map(|c| a[r][c] * v[c][i]).sum();
                    assert!((av - w[i] * v[r][i]).abs() < 1e-12 * norm, "A v != w v");
                }
                for j in 0..N {
                    let dot: f64 = (0..N).map(|r| v[r][i] * v[r][j]).sum();
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!((dot - want).abs() < 1e-12, "V not orthonormal");
                }
            }
        }
        check([[4.0, 1.0, -2.0], [1.0, 3.0, 0.5], [-2.0, 0.5, 1.0]]);
        check([[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 5.0]]);
        check([[0.0; 3]; 3]);
        check([
            [1.0, 2.0, 3.0, 4.0],
            [2.0, -1.0, 0.5, 0.0],
            [3.0, 0.5, 7.0, -2.0],
            [4.0, 0.0, -2.0, 1e-9],
        ]);
        check([[1e12, 1.0], [1.0, -1e-12]]);
    }
}
