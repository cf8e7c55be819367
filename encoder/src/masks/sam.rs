//! SAM automatic mask generation (to be implemented).
