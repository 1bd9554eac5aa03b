//! FullComm: every agent receives every other agent's full observation (with the sender's id)
//! as message columns after its own; the RNN agent reads them as part of its input. The
//! backbone is `learn.mixer` (QMIX by default).

use super::{no_settings, Messages, MethodSpec};

pub const FULLCOMM: MethodSpec = MethodSpec {
    name: "fullcomm",
    about: "FullComm: every agent receives all other agents' observations",
    messages: Messages::FullComm,
    mixer: None,
    agent_sees_state: false,
    configure: no_settings,
    settings: None,
};
