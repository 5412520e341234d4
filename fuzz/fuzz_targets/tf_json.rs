//! The transfer-function parser on arbitrary text (`--tf` files, the viewer's steering and preview bodies): a
//! valid TF or an error; a valid TF classifies every value (NaN and infinities included)
//! into colours and opacities in [0, 1].
#![no_main]

use insitu_core::tf::Lut;
use insitu_core::TransferFunction;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(tf) = TransferFunction::from_json(text, "fuzz") {
        let lut = Lut::new(&tf, 0.5);
        for v in [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -1e30,
            0.0,
            0.5,
            1.0,
            1e30,
        ] {
            let e = lut.classify(v);
            let unit = |x: f32| (0.0..=1.0).contains(&x);
            assert!(
                unit(e.alpha_unit) && unit(e.alpha_step) && e.rgb.iter().all(|&c| unit(c)),
                "{v}: {e:?}"
            );
        }
    }
});
