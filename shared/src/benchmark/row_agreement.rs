//! How well the joint tuner's learned rows agree with the truth, world
//! side: each cell's own-gate block of its `t_sr` and `w` rows (log space,
//! 1/mV) against the true Jacobian's at the same voltages. The benchmark
//! notes it per timeline point ([`super::array_timeline::before_band`]
//! sums it up); the strategy never sees it.

use serde::{Deserialize, Serialize};

/// One cell's learned own-gate rows against the true ones, per parameter
/// (`t_sr`, `w`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RowAgreement {
    /// `|g_learned| / |g_true|` (1: the right length).
    pub length_ratio: [f64; 2],
    /// Cosine of the angle between them (1: the right direction).
    pub cosine: [f64; 2],
}

impl RowAgreement {
    /// From the learned and true own-gate rows (`[t_sr, w]`, each over the
    /// cell's own gates in the same order); `None` if a row is empty, of
    /// different lengths, not finite, or a true row is zero.
    ///
    /// ```
    /// use spintune::benchmark::row_agreement::RowAgreement;
    /// let learned = [vec![0.02, 0.0], vec![0.03, 0.03]];
    /// let truth = [vec![0.01, 0.0], vec![0.03, 0.0]];
    /// let a = RowAgreement::new(&learned, &truth).unwrap();
    /// assert_eq!(a.length_ratio[0], 2.0);
    /// assert_eq!(a.cosine[0], 1.0);
    /// assert!((a.length_ratio[1] - 2f64.sqrt()).abs() < 1e-12);
    /// assert!((a.cosine[1] - 0.5f64.sqrt()).abs() < 1e-12); // 45°
    /// assert!(RowAgreement::new(&learned, &[vec![0.0, 0.0], vec![0.1, 0.0]]).is_none());
    /// ```
    pub fn new(learned: &[Vec<f64>; 2], truth: &[Vec<f64>; 2]) -> Option<Self> {
        let mut out = Self {
            length_ratio: [0.0; 2],
            cosine: [0.0; 2],
        };
        for p in 0..2 {
            let (l, t) = (&learned[p], &truth[p]);
            if l.is_empty() || l.len() != t.len() || !l.iter().chain(t).all(|x| x.is_finite()) {
                return None;
            }
            let norm = |x: &[f64]| x.iter().map(|v| v * v).sum::<f64>().sqrt();
            let (nl, nt) = (norm(l), norm(t));
            if nt == 0.0 {
                return None;
            }
            out.length_ratio[p] = nl / nt;
            out.cosine[p] = if nl == 0.0 {
                0.0
            } else {
                l.iter().zip(t).map(|(a, b)| a * b).sum::<f64>() / (nl * nt)
            };
        }
        Some(out)
    }
}
