//! The trainer: single runs (learning, export, label-free choice, self-training,
//! reproducibility and resume, refusals) and populations (halving by the label-free key,
//! reproducibility, a population of one is the single run).

mod fixtures;
mod population;
mod single;
