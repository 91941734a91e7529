//! The test suite's integration tests, one module per concern, in one binary: libtest runs
//! them from one pool, so a test that waits on a real-time peer (GRBL's firmware, a
//! browser, a daemon's timer) shares the machine with one that computes, and the suite
//! links once. `cargo test --test suite -- MODULE::` runs one module. The studies behind the
//! docs' figures, the feature-gated tests, the paper's study and `pipeline_memory` (whose
//! counting allocator must see its test alone) are binaries of their own.

#[path = "../support/mod.rs"]
mod support;

mod adversarial_clients;
mod adversarial_control;
mod adversarial_files;
mod adversarial_motion;
mod adversarial_ownership;
mod adversarial_protocol;
mod adversarial_records;
mod architecture;
mod config;
mod config_docs;
mod daemon_calibration;
mod daemon_config;
mod daemon_crash;
mod daemon_defaults;
mod daemon_diskfull;
mod daemon_fault_clear;
mod daemon_faults;
mod daemon_firmware;
mod daemon_hold;
mod daemon_jobs;
mod daemon_live_view;
mod daemon_manual;
mod daemon_plan;
mod daemon_protocol;
mod daemon_queue_disk;
mod daemon_resume;
mod daemon_xl80;
mod detect_estimate;
mod docs_examples;
mod gcs_driver;
mod grbl_conformance;
mod grbl_driver;
mod grbl_firmware;
mod partial_frames;
mod pipeline_modes;
mod process_cli;
mod protocol_schema;
mod reprocess;
mod results_report;
mod rigctl_hw;
mod rigctl_ux;
mod scan_2d;
mod tolerant_clients;
mod web_console;
mod xl80;
