//! Felzenszwalb-Huttenlocher graph segmentation (to be implemented).
