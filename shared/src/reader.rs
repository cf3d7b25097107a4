//! Range readers. Being written.
