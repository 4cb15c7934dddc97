//! Integration tests of the cli area, one binary (modules by concern).

mod demo_cli;
mod help;
