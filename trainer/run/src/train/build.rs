//! Which source tree built the running lmac: a run's `config.toml` records it (`[build]`), and a
//! resume by another build says so, since a code change can change training.

use serde::{Deserialize, Serialize};

/// The source tree of the running lmac, read from the repository it runs from.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuildInfo {
    /// The repository's commit (`git rev-parse HEAD`), or `unknown` outside a git checkout.
    pub commit: String,
    /// Tracked files differ from that commit (`git status`): the commit alone does not say
    /// what code ran.
    pub modified: bool,
}

impl BuildInfo {
    /// The repository lmac runs from, as git reports it now.
    pub fn current() -> BuildInfo {
        let unknown = BuildInfo { commit: "unknown".into(), modified: false };
        let Ok(root) = crate::supervisor::repo_root() else { return unknown };
        let git = |args: &[&str]| {
            std::process::Command::new("git")
                .arg("-C")
                .arg(&root)
                .args(args)
                .stderr(std::process::Stdio::null())
                .output()
                .ok()
                .filter(|o| o.status.success())
                .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        };
        let Some(commit) = git(&["rev-parse", "HEAD"]).filter(|c| !c.is_empty()) else { return unknown };
        let modified = git(&["status", "--porcelain", "--untracked-files=no"]).is_some_and(|s| !s.is_empty());
        BuildInfo { commit, modified }
    }

    /// What a resume should say when `self` (the run's) differs from `now` (this build's).
    pub fn difference(&self, now: &BuildInfo) -> Option<String> {
        let text = |b: &BuildInfo| format!("{}{}", b.commit, if b.modified { " (modified)" } else { "" });
        (self != now || self.modified).then(|| {
            format!(
                "this run was started by the build of {} and resumes with {}: code changes since may change how it trains",
                text(self),
                text(now)
            )
        })
    }
}
