//! A scene as a client sees it: the manifest, whose schema lives in
//! [`canopy_shared::manifest`] (the server writes it, the client reads it).

pub use canopy_shared::manifest::*;
