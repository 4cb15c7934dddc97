//! Integration tests of the piv area (modules by concern).

mod cli;
mod image_formats;
mod sim;
