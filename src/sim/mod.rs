//! Synthetic multi-camera scene simulator with ground-truth identities.
