//! The configuration reference (`lmac config reference`, `docs/reference/configuration.md`):
//! every key of `[run]`, `[learn]` and each method's `[method]`, with its default and meaning,
//! generated from the config types themselves (their doc comments and `Default`s, through their
//! JSON Schemas), so the reference cannot drift from the code. A test compares the committed
//! page with this output.

use crate::learn::methods::REGISTRY;
use crate::learn::LearnConfig;
use crate::train::config::{preset_overrides, RunSection, PRESETS};
use serde_json::Value;

/// The whole reference page, Markdown.
pub fn markdown() -> String {
    let mut out = String::new();
    out.push_str("# Configuration reference\n\n");
    out.push_str(
        "<!-- Generated from the config types' doc comments and defaults by `lmac config reference`; \
         do not edit by hand (a test compares this page with the command's output). -->\n\n",
    );
    out.push_str(
        "A run's configuration has three sections. `lmac train --config FILE` reads them from TOML, \
         `--set section.key=value` overrides one key (after `--preset`), and every run saves the \
         resolved configuration as `config.toml` in its directory. Unknown keys are errors naming \
         the key; every number has a range, checked before anything starts.\n\n",
    );
    out.push_str("```toml\n[run]\nenv = \"lbf:8x8-2p-2f-s1-coop\"\nalgo = \"qmix\"\n\n[learn]\nlr = 0.0005\n\n[method]   # the settings of run.algo's method\n```\n\n");

    out.push_str("## Presets\n\n`--preset NAME` applies these overrides before any `--set`.\n\n");
    out.push_str("| preset | overrides (of an LMAC run) | what it is |\n| --- | --- | --- |\n");
    for (name, about) in PRESETS {
        let overrides = preset_overrides(name, "lmac").map(|o| o.iter().map(|s| format!("`{s}`")).collect::<Vec<_>>().join(", "));
        out.push_str(&format!("| `{name}` | {} | {} |\n", overrides.unwrap_or_default(), cell(about)));
    }
    out.push('\n');

    section(&mut out, "[run]", "Everything about a run that is not a learner hyperparameter.", &schemars::schema_for!(RunSection));
    section(
        &mut out,
        "[learn]",
        "The learner's hyperparameters, shared by every method (defaults: the paper's Table C.3, and pymarl's QMIX where the paper is silent).",
        &schemars::schema_for!(LearnConfig),
    );

    out.push_str("## [method]\n\nThe settings of `run.algo`'s method; a key another method owns is an error.\n\n");
    for spec in REGISTRY {
        match spec.settings {
            Some(schema) => {
                out.push_str(&format!("### `{}`\n\n{}\n\n", spec.name, cell(spec.about)));
                table(&mut out, &schema());
            }
            None => out.push_str(&format!("### `{}`\n\n{}. No settings.\n\n", spec.name, cell(spec.about))),
        }
    }
    out
}

fn section(out: &mut String, title: &str, about: &str, schema: &schemars::Schema) {
    out.push_str(&format!("## {title}\n\n{about}\n\n"));
    table(out, schema);
}

/// One row per property: key, default, meaning (with an enum's values and what each means).
fn table(out: &mut String, schema: &schemars::Schema) {
    let root = schema.as_value();
    let defs = root.get("$defs").cloned().unwrap_or(Value::Null);
    let Some(props) = root.get("properties").and_then(Value::as_object) else {
        return;
    };
    out.push_str("| key | default | meaning |\n| --- | --- | --- |\n");
    for (key, prop) in props {
        let default = match prop.get("default") {
            Some(v) if !v.is_null() => format!("`{}`", toml_value(v)),
            _ => "(none)".to_string(),
        };
        let mut meaning = prop.get("description").and_then(Value::as_str).unwrap_or("").to_string();
        if let Some(choices) = enum_choices(prop, &defs) {
            if !meaning.is_empty() {
                meaning.push(' ');
            }
            meaning.push_str(&choices);
        }
        out.push_str(&format!("| `{key}` | {default} | {} |\n", cell(&meaning)));
    }
    out.push('\n');
}

/// "One of: `a` (what a is), `b`." for a property whose type is an enum, else None.
fn enum_choices(prop: &Value, defs: &Value) -> Option<String> {
    let reference =
        prop.get("$ref").or_else(|| prop.get("allOf").and_then(|a| a.get(0)).and_then(|a| a.get("$ref"))).and_then(Value::as_str)?;
    let def = defs.get(reference.rsplit('/').next()?)?;
    let mut choices = Vec::new();
    if let Some(variants) = def.get("oneOf").and_then(Value::as_array) {
        for v in variants {
            let names: Vec<&Value> = match (v.get("const"), v.get("enum").and_then(Value::as_array)) {
                (Some(c), _) => vec![c],
                (None, Some(e)) => e.iter().collect(),
                _ => continue,
            };
            for n in names {
                let desc = v.get("description").and_then(Value::as_str);
                choices.push(match desc {
                    Some(d) => format!("`{}` ({})", toml_value(n), d.trim_end_matches('.')),
                    None => format!("`{}`", toml_value(n)),
                });
            }
        }
    } else if let Some(e) = def.get("enum").and_then(Value::as_array) {
        choices.extend(e.iter().map(|n| format!("`{}`", toml_value(n))));
    }
    (!choices.is_empty()).then(|| format!("One of: {}.", choices.join("; ")))
}

/// A JSON default as it is written in TOML (strings quoted, arrays bracketed). Floats print in
/// their shortest f32 form when that reads back to the same f32 (most settings are f32, whose
/// JSON form is the widened f64: 0.10000000149011612 is 0.1).
fn toml_value(v: &Value) -> String {
    match v {
        Value::String(s) => format!("\"{s}\""),
        Value::Number(n) if n.is_f64() => {
            let x = n.as_f64().unwrap_or(f64::NAN);
            let text = if (x as f32) as f64 == x { format!("{:?}", x as f32) } else { format!("{x:?}") };
            text
        }
        Value::Array(a) => format!("[{}]", a.iter().map(toml_value).collect::<Vec<_>>().join(", ")),
        other => other.to_string(),
    }
}

/// Text for one Markdown table cell: one line, pipes escaped.
fn cell(text: &str) -> String {
    text.split_whitespace().collect::<Vec<_>>().join(" ").replace('|', "\\|")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The committed page is what the code generates: a changed doc comment or default fails
    /// here until the page is regenerated.
    #[test]
    fn committed_reference_is_current() {
        let committed = include_str!("../../../../docs/reference/configuration.md");
        assert!(
            committed == markdown(),
            "docs/reference/configuration.md is out of date: run `lmac config reference > docs/reference/configuration.md`"
        );
    }

    #[test]
    fn every_key_and_method_is_listed() {
        let page = markdown();
        for key in ["`updates_per_episode`", "`reward_standardisation`", "`lambda_cons`", "`cut`", "`prune`"] {
            assert!(page.contains(key), "{key} missing from the reference");
        }
        for spec in REGISTRY {
            assert!(page.contains(&format!("### `{}`", spec.name)), "method {} missing", spec.name);
        }
        // Defaults come from the types' Default impls.
        assert!(page.contains("| `updates_per_episode` | `1.0` |"), "{page}");
        assert!(page.contains("One of: `\"vdn\"`"), "enum choices are listed");
    }
}
