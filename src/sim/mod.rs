//! The simulated EPSNET PLC.
