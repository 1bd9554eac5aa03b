//! Reading the meta-information the design loop measured: per target dim, per-agent rates.

#[allow(unused_imports)]
use super::*;

/// Per target dim of a meta JSON: (state dim, per-agent rates, variance across agents, the
/// largest per-third variance with its third), with communication.
pub(super) struct MetaDim {
    pub(super) dim: usize,
    /// E[chi] of a constant guess (0 when the JSON does not say).
    pub(super) guess: f64,
    pub(super) rates: Vec<f64>,
    pub(super) rates_without: Vec<f64>,
    pub(super) variance: f64,
    pub(super) worst_third: (f64, &'static str),
}

pub(super) fn parse_dim(label: &str) -> Option<usize> {
    let rest = label.strip_prefix("s[")?;
    rest[..rest.find(']')?].parse().ok()
}

pub(super) fn floats(v: &Value) -> Vec<f64> {
    v.as_array().map(|a| a.iter().filter_map(|x| x.as_f64()).collect()).unwrap_or_default()
}

pub(super) fn meta_dims(meta: &Value) -> Result<Vec<MetaDim>> {
    let dims = meta["dimensions"].as_array().ok_or_else(|| anyhow!("the meta-information has no \"dimensions\" list"))?;
    dims.iter()
        .enumerate()
        .map(|(k, d)| {
            let label = d["dimension"].as_str().unwrap_or_default();
            let dim = parse_dim(label)
                .ok_or_else(|| anyhow!("meta-information dimensions[{k}]: \"dimension\" {label:?} does not start with s[<index>]"))?;
            let w = &d["with_communication"];
            let rates = floats(&w["agent_success_rates"]);
            if rates.is_empty() {
                bail!("meta-information dimensions[{k}] ({label}): with_communication.agent_success_rates is missing or empty");
            }
            let worst_third = meta::THIRDS
                .iter()
                .map(|th| (w[format!("variance_in_{th}")].as_f64().unwrap_or(0.0), *th))
                .fold((f64::MIN, "early"), |a, b| if b.0 > a.0 { b } else { a });
            Ok(MetaDim {
                dim,
                guess: d["constant_guess_rate"].as_f64().unwrap_or(0.0),
                variance: meta::variance(&rates),
                rates,
                rates_without: floats(&d["without_communication"]["agent_success_rates"]),
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
