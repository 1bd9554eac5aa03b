//! Reading the meta-information the design loop measured: per target dim, per-agent rates.

use crate::meta;
use crate::meta_info::MetaInfo;
use anyhow::{bail, Result};

/// Per target dim of the meta-information: (state dim, per-agent rates, variance across agents,
/// the largest per-third variance with its third), with communication.
pub(super) struct MetaDim {
    pub(super) dim: usize,
    /// E[chi] of a constant guess.
    pub(super) guess: f64,
    pub(super) rates: Vec<f64>,
    pub(super) rates_without: Vec<f64>,
    pub(super) variance: f64,
    pub(super) worst_third: (f64, &'static str),
}

pub(super) fn meta_dims(meta: &MetaInfo) -> Result<Vec<MetaDim>> {
    meta.dimensions
        .iter()
        .enumerate()
        .map(|(k, d)| {
            let w = &d.with_communication;
            let rates = w.agent_success_rates.clone();
            if rates.is_empty() {
                bail!("meta-information dimensions[{k}] ({}): with_communication.agent_success_rates is empty", d.dimension);
            }
            let in_third = |th: usize| (w.third(th).1, meta::THIRDS[th]);
            let worst_third = (0..3).map(in_third).fold((f64::MIN, "early"), |a, b| if b.0 > a.0 { b } else { a });
            Ok(MetaDim {
                dim: d.dim,
                guess: d.constant_guess_rate,
                variance: meta::variance(&rates),
                rates,
                rates_without: d.without_communication.agent_success_rates.clone(),
                worst_third,
            })
        })
        .collect()
}

impl MetaDim {
    pub(super) fn skill(&self) -> f64 {
        meta::skill(meta::mean(&self.rates), self.guess)
    }
}

/// Failure of rate `r` on the scale of the constant guess's failure, in [0, 1] (0 for a dim the
/// guess always gets right: nothing to gain there).
pub(super) fn failure(r: f64, guess: f64) -> f64 {
    if guess >= 1.0 - 1e-9 {
        0.0
    } else {
        ((1.0 - r) / (1.0 - guess)).clamp(0.0, 1.0)
    }
}

pub(super) fn fmt_rates(r: &[f64]) -> String {
    format!("[{}]", r.iter().map(|x| format!("{x:.2}")).collect::<Vec<_>>().join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::meta_info::{example, MetaInfo};

    #[test]
    fn meta_info_round_trips_and_dims_come_from_the_number() {
        // Labels that disagree with the index: the designer must read the numeric field.
        let meta = example(&[(7, "s[62] - a label".into()), (9, "no index here".into())], &[0.9, 0.4], &[0.5, 0.5]);
        let text = serde_json::to_string_pretty(&meta.json()).unwrap();
        let back: MetaInfo = serde_json::from_str(&text).unwrap();
        assert_eq!(back, meta);
        // The keys the plot script and the prompts have always read, plus the numeric dim.
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(v["summary"]["target_dims"], serde_json::json!([7, 9]));
        assert_eq!(v["summary"]["with_communication"]["mean_recovery"], 0.65);
        assert_eq!(v["dimensions"][0]["dim"], 7);
        assert_eq!(v["dimensions"][0]["dimension"], "s[62] - a label");
        assert_eq!(v["dimensions"][0]["with_communication"]["variance_in_late"], 0.0625);
        assert_eq!(v["discriminators"]["config"]["hidden"], 64);
        let dims = meta_dims(&back).unwrap();
        assert_eq!(dims.iter().map(|d| d.dim).collect::<Vec<_>>(), vec![7, 9]);
        assert_eq!((dims[0].rates.as_slice(), dims[0].rates_without.as_slice(), dims[0].guess), (&[0.9, 0.4][..], &[0.5, 0.5][..], 0.5));
        // A key that is not part of the meta-information is refused, naming it.
        let e = serde_json::from_str::<MetaInfo>(&text.replacen("\"alpha\"", "\"alfa\"", 1)).unwrap_err().to_string();
        assert!(e.contains("alfa"), "{e}");
    }
}
