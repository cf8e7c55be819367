//! PIL-compatible image resampling for SAM/CLIP preprocessing (to be implemented).
