//! The message plan a run uses, as one value: a built-in or protocol files. `run.protocol`, the
//! `--protocol` of every process of a run and the trainer's message check all go through
//! [`ProtocolSpec`], so the text form (`none`, `fullcomm`, `a.json+b.json`) is parsed in one place.

use std::fmt;
use std::str::FromStr;

/// A resolved protocol: what the runner writes into the message columns.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ProtocolSpec {
    /// No message columns.
    None,
    /// Every agent receives every other agent's observation (the FullComm baseline).
    FullComm,
    /// Protocol files (JSON), the design's phases in order; the final protocol concatenates
    /// their messages.
    Files(Vec<String>),
}

impl ProtocolSpec {
    /// The protocol files, none for a built-in.
    pub fn files(&self) -> &[String] {
        match self {
            ProtocolSpec::Files(f) => f,
            _ => &[],
        }
    }

    /// The same files, each mapped by `f` (e.g. to absolute paths); built-ins stay as they are.
    pub fn map_files<E>(&self, f: impl FnMut(&str) -> Result<String, E>) -> Result<ProtocolSpec, E> {
        Ok(match self {
            ProtocolSpec::Files(files) => ProtocolSpec::Files(files.iter().map(|s| s.as_str()).map(f).collect::<Result<_, E>>()?),
            other => other.clone(),
        })
    }
}

impl FromStr for ProtocolSpec {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        match text {
            "none" => Ok(ProtocolSpec::None),
            "fullcomm" => Ok(ProtocolSpec::FullComm),
            _ => {
                let files: Vec<String> = text.split('+').map(str::to_string).collect();
                if files.iter().all(|f| f.len() > ".json".len() && f.ends_with(".json")) {
                    Ok(ProtocolSpec::Files(files))
                } else {
                    Err(format!("unknown protocol {text:?}: use 'none', 'fullcomm' or protocol files (a.json or a.json+b.json)"))
                }
            }
        }
    }
}

impl fmt::Display for ProtocolSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ProtocolSpec::None => f.write_str("none"),
            ProtocolSpec::FullComm => f.write_str("fullcomm"),
            ProtocolSpec::Files(files) => f.write_str(&files.join("+")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_text_forms_round_trip() {
        for text in ["none", "fullcomm", "p0.json", "/d/phase0/protocol.json+/d/phase1/protocol.json"] {
            let spec: ProtocolSpec = text.parse().unwrap();
            assert_eq!(spec.to_string(), text);
        }
        assert_eq!("a.json+b.json".parse::<ProtocolSpec>().unwrap().files(), ["a.json", "b.json"]);
        assert!("fullcomm".parse::<ProtocolSpec>().unwrap().files().is_empty());
    }

    #[test]
    fn anything_else_is_refused_with_the_forms_it_takes() {
        for bad in ["", "full", "a.json+", "a.json+b.toml", ".json", "designs/x"] {
            let e = bad.parse::<ProtocolSpec>().unwrap_err();
            assert!(e.contains("'none', 'fullcomm' or protocol files"), "{bad:?}: {e}");
        }
    }

    #[test]
    fn map_files_changes_only_the_files() {
        let spec: ProtocolSpec = "a.json+b.json".parse().unwrap();
        let mapped = spec.map_files(|f| Ok::<_, ()>(format!("/abs/{f}"))).unwrap();
        assert_eq!(mapped.to_string(), "/abs/a.json+/abs/b.json");
        assert_eq!(ProtocolSpec::None.map_files(|f| Ok::<_, ()>(f.to_string())).unwrap(), ProtocolSpec::None);
    }
}
