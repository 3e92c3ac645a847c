//! Fuzz target (c): a data dir with one file's bytes replaced, opened and used.
#![no_main]
libfuzzer_sys::fuzz_target!(
    init: tamrm_fuzz::seeds::write_if_asked("disk"),
    |data: &[u8]| {
        tamrm_fuzz::targets::disk(data);
    }
);
