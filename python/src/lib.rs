//! `ebptv._ebptv`, the extension module of the `ebptv` Python package
//! (python/ebptv). The bindings live in the library (`ebptv::python`,
//! feature `python`), next to the internals they call.

use pyo3::prelude::*;

#[pymodule]
fn _ebptv(m: &Bound<'_, PyModule>) -> PyResult<()> {
    ebptv::python::register(m)
}
