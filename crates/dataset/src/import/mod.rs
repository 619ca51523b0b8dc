//! Importers from other formats into the pgrd dataset format.

pub mod deform;
pub mod phystwin;
pub mod pickle;
