//! Integration tests of the modelcheck area: the `ebptv modelcheck` command.
//! (The building blocks are unit-tested in `src/modelcheck/tests/`.)

mod cli;
