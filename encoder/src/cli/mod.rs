//! Command-line argument structs and run functions of `slag-encoder` subcommands.

pub mod shards;
