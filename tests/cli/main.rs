//! Integration tests of the cli area, one binary (modules by concern).

mod demo_cli;
mod plot_figures;
mod help;
