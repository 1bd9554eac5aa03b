//! Fields whose value is constant by construction, found from the expression alone (no
//! dataset): `{"const": 0}`, `{"mul": [x, {"const": 0}]}`, a window over a constant, a clip to
//! one value, an operator of two constants. Such a column reaches every receiver with the same
//! value at every step, so it carries nothing; `lmac protocol check` and `explain` report it
//! (the dataset-based dead-field check finds the fields that are constant in practice).
//!
//! The analysis is conservative: a column is called constant only when every value the sender
//! can compute is the same (observations, last actions and the sender's id vary).

use super::ast::*;
use super::ProtocolEnv;

/// One output column of an expression, as far as the analysis can tell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ColumnKind {
    /// Depends on what the sender observes (or on which agent sends it).
    Varying,
    /// The same at every step for every sender; the value when the analysis can compute it.
    Constant(Option<f64>),
}

/// A field with columns that are constant by construction.
#[derive(Debug, Clone, PartialEq)]
pub struct ConstantField {
    pub field: String,
    pub width: usize,
    /// (column within the field, its value when known)
    pub columns: Vec<(usize, Option<f64>)>,
}

impl ConstantField {
    /// One line for a person: which columns, which values, and that they carry nothing.
    pub fn describe(&self) -> String {
        let which = if self.columns.len() == self.width {
            format!("all {} column(s)", self.width)
        } else {
            let cols: Vec<String> = self.columns.iter().map(|(c, _)| c.to_string()).collect();
            format!("column(s) {} of {}", cols.join(", "), self.width)
        };
        let mut values: Vec<String> = self.columns.iter().map(|(_, v)| v.map_or("?".to_string(), |x| format!("{x}"))).collect();
        values.dedup();
        format!(
            "field `{}`: {which} constant by construction (value {}): the same for every sender at every step, so it carries nothing",
            self.field,
            values.join(", ")
        )
    }
}

/// The fields of `p` with constant columns (in field order). Needs the env for the widths of
/// `last_action` and `sender_one_hot`; an expression that does not validate is skipped (the
/// validator reports it).
pub fn constant_fields(p: &Protocol, env: &ProtocolEnv) -> Vec<ConstantField> {
    p.fields
        .iter()
        .filter_map(|f| {
            let cols = columns(&f.value, env)?;
            let constant: Vec<(usize, Option<f64>)> = cols
                .iter()
                .enumerate()
                .filter_map(|(i, c)| match c {
                    ColumnKind::Constant(v) => Some((i, *v)),
                    ColumnKind::Varying => None,
                })
                .collect();
            (!constant.is_empty()).then(|| ConstantField { field: f.name.clone(), width: cols.len(), columns: constant })
        })
        .collect()
}

/// Lines describing the constant fields of every phase (empty when there are none).
pub fn constant_fields_report(phases: &[Protocol], env: &ProtocolEnv) -> Vec<String> {
    let mut out = Vec::new();
    for (k, p) in phases.iter().enumerate() {
        for c in constant_fields(p, env) {
            out.push(format!("warning: phase {}: {}", p.phase.map_or(k as u32, |x| x), c.describe()));
        }
    }
    out
}

/// The columns of `e` (None: the expression does not fit the env; the validator says why).
pub fn columns(e: &Expr, env: &ProtocolEnv) -> Option<Vec<ColumnKind>> {
    use ColumnKind::*;
    Some(match e {
        Expr::Obs(dims) => vec![Varying; dims.len()],
        Expr::ObsSlice(s) => vec![Varying; s.end.checked_sub(s.start)?],
        Expr::LastAction(ActionEncoding::OneHot) => vec![Varying; env.n_actions],
        Expr::LastAction(ActionEncoding::Index) => vec![Varying],
        // Constant for one sender, but a field's column differs between senders and receivers
        // cannot place a sender without it: not called constant.
        Expr::SenderOneHot => vec![Varying; env.n_agents],
        Expr::Const(c) => vec![Constant(Some(*c))],
        Expr::Window(w) => {
            // Any aggregate of a sequence that is the same at every step (padding included: a
            // constant expression evaluates to itself there) is the same at every step.
            let inner = columns(&w.of, env)?;
            inner
                .into_iter()
                .map(|c| match c {
                    Constant(v) => Constant(v.and_then(|x| window_value(w.op, w.k, x))),
                    Varying => Varying,
                })
                .collect()
        }
        Expr::Neg(a) => map(columns(a, env)?, |x| -x),
        Expr::Abs(a) => map(columns(a, env)?, f64::abs),
        Expr::Clip(c) => {
            if c.min == c.max {
                vec![Constant(Some(c.min)); columns(&c.of, env)?.len()]
            } else {
                map(columns(&c.of, env)?, |x| x.clamp(c.min, c.max.max(c.min)))
            }
        }
        Expr::Reduce(r) => {
            let cols = columns(&r.of, env)?;
            if cols.iter().all(|c| matches!(c, Constant(_))) {
                let vals: Option<Vec<f64>> = cols.iter().map(|c| if let Constant(v) = c { *v } else { None }).collect();
                vec![Constant(vals.filter(|v| !v.is_empty()).map(|v| reduce_value(r.op, &v)))]
            } else {
                vec![Varying]
            }
        }
        Expr::Concat(parts) => {
            let mut out = Vec::new();
            for p in parts {
                out.extend(columns(p, env)?);
            }
            out
        }
        other => {
            let (op, a, b) = other.binary()?;
            let (a, b) = (columns(a, env)?, columns(b, env)?);
            let width = match (a.len(), b.len()) {
                (x, y) if x == y => x,
                (1, y) => y,
                (x, 1) => x,
                _ => return None,
            };
            let at = |v: &[ColumnKind], i: usize| if v.len() == 1 { v[0] } else { v[i] };
            (0..width).map(|i| binary(op, at(&a, i), at(&b, i))).collect()
        }
    })
}

fn map(cols: Vec<ColumnKind>, f: impl Fn(f64) -> f64) -> Vec<ColumnKind> {
    cols.into_iter()
        .map(|c| match c {
            ColumnKind::Constant(v) => ColumnKind::Constant(v.map(&f)),
            ColumnKind::Varying => ColumnKind::Varying,
        })
        .collect()
}

fn binary(op: BinOp, a: ColumnKind, b: ColumnKind) -> ColumnKind {
    use ColumnKind::*;
    match (a, b) {
        (Constant(Some(x)), Constant(Some(y))) => Constant(Some(apply(op, x, y))),
        (Constant(_), Constant(_)) => Constant(None),
        // x * 0 = 0 and 0 / y = 0 (div gives 0 where |y| < 1e-6 too), whatever x and y are
        (Constant(Some(z)), Varying) | (Varying, Constant(Some(z))) if op == BinOp::Mul && z == 0.0 => Constant(Some(0.0)),
        (Constant(Some(z)), Varying) if op == BinOp::Div && z == 0.0 => Constant(Some(0.0)),
        (Varying, Constant(Some(y))) if op == BinOp::Div && y.abs() < 1e-6 => Constant(Some(0.0)),
        _ => Varying,
    }
}

/// The operators' semantics as the compiled plan computes them (`compile.rs`).
fn apply(op: BinOp, x: f64, y: f64) -> f64 {
    match op {
        BinOp::Add => x + y,
        BinOp::Sub => x - y,
        BinOp::Mul => x * y,
        BinOp::Div => {
            if y.abs() < 1e-6 {
                0.0
            } else {
                x / y
            }
        }
        BinOp::Min => x.min(y),
        BinOp::Max => x.max(y),
        BinOp::Gt => (x > y) as u8 as f64,
        BinOp::Lt => (x < y) as u8 as f64,
        BinOp::Eq => ((x - y).abs() < 1e-6) as u8 as f64,
    }
}

fn window_value(op: WindowOp, k: usize, x: f64) -> Option<f64> {
    Some(match op {
        WindowOp::Mean | WindowOp::Min | WindowOp::Max | WindowOp::Last => x,
        WindowOp::Sum => x * k as f64,
        WindowOp::Delta => 0.0,
        WindowOp::LastNonzero => {
            if x != 0.0 {
                x
            } else {
                0.0
            }
        }
    })
}

fn reduce_value(op: ReduceOp, v: &[f64]) -> f64 {
    match op {
        ReduceOp::Sum => v.iter().sum(),
        ReduceOp::Mean => v.iter().sum::<f64>() / v.len() as f64,
        ReduceOp::Min => v.iter().cloned().fold(f64::INFINITY, f64::min),
        ReduceOp::Max => v.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env() -> ProtocolEnv {
        ProtocolEnv::new(3, 6, 5, 4, 64)
    }

    fn expr(json: &str) -> Expr {
        serde_json::from_str(json).expect("expression parses")
    }

    #[test]
    fn constants_are_found_through_the_operators_and_varying_inputs_are_not() {
        let e = env();
        use ColumnKind::*;
        for (json, want) in [
            (r#"{"const": 0}"#, vec![Constant(Some(0.0))]),
            (r#"{"obs": [1, 2]}"#, vec![Varying, Varying]),
            (r#"{"mul": [{"obs": [1, 2]}, {"const": 0}]}"#, vec![Constant(Some(0.0)); 2]),
            (r#"{"mul": [{"obs": [1, 2]}, {"const": 2}]}"#, vec![Varying; 2]),
            (r#"{"add": [{"const": 1}, {"const": 2}]}"#, vec![Constant(Some(3.0))]),
            (r#"{"window": {"op": "sum", "k": 4, "of": {"const": 0.5}}}"#, vec![Constant(Some(2.0))]),
            (r#"{"window": {"op": "mean", "k": 4, "of": {"obs": [0]}}}"#, vec![Varying]),
            (r#"{"clip": {"of": {"obs": [3]}, "min": 1, "max": 1}}"#, vec![Constant(Some(1.0))]),
            (r#"{"concat": [{"obs": [0]}, {"const": 9}]}"#, vec![Varying, Constant(Some(9.0))]),
            (r#"{"reduce": {"op": "max", "of": {"concat": [{"const": 1}, {"const": 4}]}}}"#, vec![Constant(Some(4.0))]),
            (r#"{"div": [{"obs": [0]}, {"const": 0}]}"#, vec![Constant(Some(0.0))]),
            ("\"sender_one_hot\"", vec![Varying; 3]),
            (r#"{"last_action": "one_hot"}"#, vec![Varying; 5]),
        ] {
            assert_eq!(columns(&expr(json), &e), Some(want), "{json}");
        }
    }

    #[test]
    fn a_protocol_with_a_constant_field_is_reported_naming_the_field() {
        let p: Protocol = serde_json::from_str(
            r#"{"message_design_instruction": "x", "critical_state_dims": [0], "fields": [
                {"name": "pos", "description": "d", "value": {"obs": [0, 1]}},
                {"name": "anchor", "description": "placeholder", "value": {"concat": [{"const": 0}, {"const": 0}]}},
                {"name": "mixed", "description": "d", "value": {"concat": [{"obs": [2]}, {"const": 7}]}}]}"#,
        )
        .unwrap();
        let found = constant_fields(&p, &env());
        assert_eq!(found.len(), 2, "{found:?}");
        assert_eq!(found[0].field, "anchor");
        assert!(found[0].describe().contains("all 2 column(s) constant by construction (value 0)"), "{}", found[0].describe());
        assert_eq!(found[1].columns, vec![(1, Some(7.0))]);
        assert!(found[1].describe().contains("column(s) 1 of 2"), "{}", found[1].describe());
    }
}
