//! CLIP text tower + BPE tokenizer (to be implemented).
