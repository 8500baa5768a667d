//! The fuzz targets' checks, shared with the stable regression tests.

pub mod checks;

#[global_allocator]
static ALLOC: checks::alloc_count::Counting = checks::alloc_count::Counting;
pub mod s7_checks;
