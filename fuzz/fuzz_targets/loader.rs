//! libFuzzer target: see `deform_target_core::testkit::fuzz::loader`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    deform_target_core::testkit::fuzz::loader(data);
});
