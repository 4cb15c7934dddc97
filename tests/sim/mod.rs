//! Integration tests of the sim area (modules by concern).

mod calibration;
mod cli;
mod determinism;
mod effects;
mod scenario;
mod stats;
mod truth;
