//! Output: per-vertex radiosity, EXR, PLY and preview images.
