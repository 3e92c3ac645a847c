//! Fuzz target (a): raw `ShapeRequest` sequences through a live `Shape` stream.
#![no_main]
libfuzzer_sys::fuzz_target!(
    init: tamrm_fuzz::seeds::write_if_asked("shape_stream"),
    |data: &[u8]| {
        tamrm_fuzz::runtime().block_on(tamrm_fuzz::targets::shape_stream(data));
    }
);
