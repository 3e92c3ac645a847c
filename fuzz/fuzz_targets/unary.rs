//! Fuzz target (b): raw requests to every unary method.
#![no_main]
libfuzzer_sys::fuzz_target!(
    init: tamrm_fuzz::seeds::write_if_asked("unary"),
    |data: &[u8]| {
        tamrm_fuzz::runtime().block_on(tamrm_fuzz::targets::unary(data));
    }
);
