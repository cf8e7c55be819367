//! `slag-encoder` command line (to be implemented).
fn main() {}
