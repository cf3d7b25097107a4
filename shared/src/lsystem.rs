//! Stochastic parametric L-systems (seed 000). Being written.
