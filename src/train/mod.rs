//! Training: losses, the optimizer, and (later) density control and the stages.

pub mod loss;
pub mod optim;
