//! Every pure-Rust volume reader on arbitrary bytes: the first byte picks the format (NetCDF
//! classic, NRRD, VTK XML, legacy VTK, XDMF), the rest is the file. Opening and reading the first step give a volume
//! of the dims the file claims, or an error; never a panic, and never an allocation the file's
//! bytes do not justify (libFuzzer's malloc limit catches one). The read limit is set to
//! 64 MiB, so a claimed volume over it is refused by the limit's check rather than by
//! libFuzzer's.
#![no_main]

use insitu_readers::{open, Options};
use libfuzzer_sys::fuzz_target;

const FORMATS: [&str; 5] = ["nc", "nrrd", "vti", "vtk", "xmf"];

fuzz_target!(|data: &[u8]| {
    static LIMIT: std::sync::Once = std::sync::Once::new();
    // Set once, before any read, on libFuzzer's one thread.
    LIMIT.call_once(|| std::env::set_var(insitu_readers::limit::ENV, "64MiB"));
    let Some((&pick, file)) = data.split_first() else {
        return;
    };
    let ext = FORMATS[usize::from(pick) % FORMATS.len()];
    let dir = std::env::temp_dir().join(format!("insitu-fuzz-readers-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let path = dir.join(format!("input.{ext}"));
    if std::fs::write(&path, file).is_err() {
        return;
    }
    for field in [None, Some("a".to_owned())] {
        if let Ok(d) = open(&path, &Options { field, ..Options::default() }) {
            if let Ok(v) = d.read_step(0) {
                assert_eq!(v.dims(), d.dims);
            }
        }
    }
});
