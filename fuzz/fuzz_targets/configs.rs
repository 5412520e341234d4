//! The three daemons' TOML configs on arbitrary text: parsed and validated, or refused with
//! an error naming the key; never a panic.
#![no_main]

use insitu_proto::daemon::DaemonConfig;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(c) = toml::from_str::<insitu_generator_node::config::Config>(text) {
        let _ = c.validate();
    }
    if let Ok(c) = toml::from_str::<insitu_viz_node::Config>(text) {
        let _ = c.validate();
    }
    if let Ok(c) = toml::from_str::<insitu_tuner_node::config::Config>(text) {
        let _ = c.validate();
    }
});
