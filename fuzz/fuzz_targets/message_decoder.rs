//! libFuzzer target: see `deform_target_core::testkit::fuzz::message_decoder`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    deform_target_core::testkit::fuzz::message_decoder(data);
});
