#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| plccoms_fuzz::checks::opcua_structure(data));
