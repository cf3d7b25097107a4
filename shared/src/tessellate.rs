//! Tessellation of skeletons and leaves. Being written.
