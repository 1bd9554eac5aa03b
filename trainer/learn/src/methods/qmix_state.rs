//! QMIX+State: each agent's input also holds the global state, an upper bound on what any
//! message could tell it. The backbone is `learn.mixer` (QMIX by default).

use super::{no_settings, Messages, MethodSpec};

pub const QMIX_STATE: MethodSpec = MethodSpec {
    name: "qmix-state",
    about: "QMIX+State: agents also see the global state (an upper bound)",
    messages: Messages::Optional,
    mixer: None,
    agent_sees_state: true,
    configure: no_settings,
    settings: None,
};
