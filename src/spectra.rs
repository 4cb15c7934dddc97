//! Power spectra of time-resolved fields (Welch, rustfft).
//!
//! (Design notes to be written with the implementation.)
