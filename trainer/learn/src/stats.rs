//! The few statistics several parts of lmac need, each written once: mean, population variance,
//! the sample SD, median and quantiles of a list, and per-column moments of row-major data (standardising discriminator
//! inputs and targets, correlations in the offline designer).

/// Mean (0 for an empty list).
pub fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// Population variance (0 for an empty list).
pub fn variance(v: &[f64]) -> f64 {
    let m = mean(v);
    v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / v.len().max(1) as f64
}

/// Sample standard deviation (n - 1 in the divisor; 0 for fewer than two values): the spread
/// over seeds every report and table states.
pub fn sample_sd(v: &[f64]) -> f64 {
    if v.len() < 2 {
        return 0.0;
    }
    (variance(v) * v.len() as f64 / (v.len() - 1) as f64).sqrt()
}

/// Median (the upper one of an even count; 0 for an empty list); NaNs sort last.
pub fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// The q-quantile (q in [0, 1]) as the sorted list's element at round((len - 1) q), no
/// interpolation (NaN for an empty list).
pub fn quantile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(|a, b| a.total_cmp(b));
    s[(((s.len() - 1) as f64 * q).round() as usize).min(s.len() - 1)]
}

/// Per-column mean and population standard deviation of rows of `width` values.
#[derive(Clone, Debug, PartialEq)]
pub struct ColumnMoments {
    pub mean: Vec<f64>,
    pub sd: Vec<f64>,
}

impl ColumnMoments {
    /// Over `rows` (each at least `width` long); no rows gives means 0 and deviations 0.
    pub fn of_rows<R: AsRef<[f32]>>(width: usize, rows: impl IntoIterator<Item = R>) -> Self {
        let mut sums = ColumnSums::new(width);
        for r in rows {
            sums.add(&r.as_ref()[..width]);
        }
        sums.finish()
    }

    /// Over the first `rows` rows of a flat row-major buffer.
    pub fn of_flat(v: &[f32], width: usize, rows: usize) -> Self {
        Self::of_rows(width, v.chunks_exact(width.max(1)).take(rows))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn column_moments_match_the_definition() {
        let m = ColumnMoments::of_flat(&[1.0, 10.0, 3.0, 10.0, 5.0, 10.0], 2, 3);
        assert_eq!(m.mean, vec![3.0, 10.0]);
        assert!((m.sd[0] - (8.0f64 / 3.0).sqrt()).abs() < 1e-12 && m.sd[1] == 0.0);
        assert_eq!((mean(&[1.0, 2.0, 6.0]), variance(&[1.0, 3.0])), (3.0, 1.0));
        assert_eq!(ColumnMoments::of_rows::<&[f32]>(2, []), ColumnMoments { mean: vec![0.0; 2], sd: vec![0.0; 2] });
    }
}

/// Per-column sums of rows added one at a time, for data that streams past instead of being
/// held ([`ColumnMoments::of_rows`] is these sums over an iterator).
#[derive(Clone, Debug)]
pub struct ColumnSums {
    sum: Vec<f64>,
    sq: Vec<f64>,
    rows: usize,
}

impl ColumnSums {
    pub fn new(width: usize) -> Self {
        ColumnSums { sum: vec![0.0; width], sq: vec![0.0; width], rows: 0 }
    }

    /// One row of `width` values.
    pub fn add(&mut self, row: &[f32]) {
        for ((s, q), &x) in self.sum.iter_mut().zip(&mut self.sq).zip(row) {
            let x = x as f64;
            *s += x;
            *q += x * x;
        }
        self.rows += 1;
    }

    /// Mean and population standard deviation of the rows added (0 and 0 for none).
    pub fn finish(&self) -> ColumnMoments {
        let n = self.rows.max(1) as f64;
        let mean: Vec<f64> = self.sum.iter().map(|s| s / n).collect();
        let sd = self.sq.iter().zip(&mean).map(|(q, m)| (q / n - m * m).max(0.0).sqrt()).collect();
        ColumnMoments { mean, sd }
    }
}
