//! Closed-form configuration factors: the validation catalogue.
