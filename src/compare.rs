//! PTV-versus-PIV comparison on the same grid.
//!
//! (Design notes to be written with the implementation.)
