//! Integration tests of the ptv area (modules by concern).

mod cli;
mod sim;
mod vortex_core;
