//! The instance pack lives in `canopy_shared::pack`: the server writes it, clients read tiles of
//! it by range, so both use the one implementation.

pub use canopy_shared::pack::*;
