//! The step engine's tests on scripted devices (`fake`): every way a step can end, in
//! milliseconds, with no emulator, socket or wall-clock wait. The fakes are test code only:
//! they exist in `cargo test` builds of the library and nowhere else.

mod engine;
mod fake;
mod plan;
