//! The per-Gaussian embeddings file (safetensors) (to be implemented).
