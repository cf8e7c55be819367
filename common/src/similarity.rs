//! Cosine similarity between a text embedding and per-Gaussian embeddings (to be implemented).
