//! Integration tests of the pulses area (modules by concern).

mod cli;
mod live;
mod sim;
mod simulator;
