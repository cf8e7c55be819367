//! Shared helpers for slag's end-to-end tests.
