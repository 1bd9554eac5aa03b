//! QMIX, VDN and QPLEX (Rashid et al. 2018; Sunehag et al. 2017; Wang et al. 2021): pymarl's RNN
//! agent on its own observation, its last action and its id, mixed by the named backbone. No
//! messages, unless `run.protocol` gives protocol files ("QMIX with messages": the message
//! columns join the observation).

use super::{no_settings, Messages, MethodSpec};
use crate::config::MixerKind;

pub const QMIX: MethodSpec = MethodSpec {
    name: "qmix",
    about: "QMIX: RNN agents, monotonic hypernetwork mixer, no messages",
    messages: Messages::Optional,
    mixer: Some(MixerKind::Qmix),
    agent_sees_state: false,
    configure: no_settings,
    settings: None,
};

pub const VDN: MethodSpec = MethodSpec {
    name: "vdn",
    about: "VDN: RNN agents, Q_tot = sum of the agents' Q, no messages",
    messages: Messages::Optional,
    mixer: Some(MixerKind::Vdn),
    agent_sees_state: false,
    configure: no_settings,
    settings: None,
};

pub const QPLEX: MethodSpec = MethodSpec {
    name: "qplex",
    about: "QPLEX: RNN agents, duplex dueling attention mixer, no messages",
    messages: Messages::Optional,
    mixer: Some(MixerKind::Qplex),
    agent_sees_state: false,
    configure: no_settings,
    settings: None,
};
