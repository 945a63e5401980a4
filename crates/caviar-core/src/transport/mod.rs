//! Transports: how modules that run outside this process take part in an episode.
//! Each transport is a folder of its own and a leaf of the crate: it uses the engine,
//! the configuration and module assembly, and nothing above it uses its internals
//! (the run prepares it through [`nats::prepare`]).

pub mod nats;
