//! Integration tests of the cli area (modules by concern).

mod demo_cli;
mod help;
