//! Training: losses, the optimizer, density control, and the stages.

pub mod checkpoint;
pub mod config;
pub mod density;
pub mod dynamic_run;
pub mod dynamic_stage;
pub mod init;
pub mod loss;
pub mod optim;
pub mod revealed;
pub mod rigidity;
pub mod static_stage;
pub mod track;
pub mod views;
