//! CLIP crop embeddings (to be implemented).
