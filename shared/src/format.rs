//! Progressive tree format. Being written.
