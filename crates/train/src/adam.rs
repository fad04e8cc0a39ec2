//! Adam (Kingma & Ba) over candle variables, with its moment state exposed so that
//! checkpoints can save and restore it exactly.
use candle_core::backprop::GradStore;
use candle_core::{Tensor, Var};

use crate::model::ce;
use crossview_core::Result;

/// Adam with PyTorch's defaults (β1 0.9, β2 0.999, ε 1e-8) and no weight decay.
#[derive(Debug)]
pub struct Adam {
    vars: Vec<(String, Var)>,
    /// First moments, one per variable.
    pub m: Vec<Tensor>,
    /// Second moments, one per variable.
    pub v: Vec<Tensor>,
    /// Steps taken so far (bias correction).
    pub t: u64,
    /// Current learning rate.
    pub lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
}

impl Adam {
    /// A fresh optimiser over named variables.
    pub fn new(vars: Vec<(String, Var)>, lr: f64) -> Result<Self> {
        let zeros = |v: &Var| v.zeros_like().map_err(ce);
        let m = vars.iter().map(|(_, v)| zeros(v)).collect::<Result<_>>()?;
        let v2 = vars.iter().map(|(_, v)| zeros(v)).collect::<Result<_>>()?;
        Ok(Adam {
            vars,
            m,
            v: v2,
            t: 0,
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        })
    }

    /// This optimiser's state (moments, step count, learning rate) over `vars`, the
    /// variables of a copy of the model it optimises (same names, same order).
    pub fn clone_for(&self, vars: Vec<(String, Var)>) -> Self {
        debug_assert!(vars.iter().map(|(n, _)| n.as_str()).eq(self.names()));
        Adam {
            vars,
            m: self.m.clone(),
            v: self.v.clone(),
            ..*self
        }
    }

    /// Names of the optimised variables, in order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.vars.iter().map(|(n, _)| n.as_str())
    }

    /// One update from the gradients of the last backward pass (variables without a
    /// gradient are left unchanged).
    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        self.t += 1;
        let bc1 = 1.0 - self.beta1.powi(self.t as i32);
        let bc2 = 1.0 - self.beta2.powi(self.t as i32);
        let step_size = self.lr / bc1;
        for (i, (_, var)) in self.vars.iter().enumerate() {
            let Some(g) = grads.get(var.as_tensor()) else {
                continue;
            };
            // Gradients carry the graph that produced them: detach so the moments do not
            // keep every past step's graph alive.
            let g = g.detach();
            let g = &g;
            let run = || -> candle_core::Result<(Tensor, Tensor)> {
                let m = ((&self.m[i] * self.beta1)? + (g * (1.0 - self.beta1))?)?;
                let v = ((&self.v[i] * self.beta2)? + (g.sqr()? * (1.0 - self.beta2))?)?;
                let denom = ((&v / bc2)?.sqrt()? + self.eps)?;
                let update = ((&m / &denom)? * step_size)?;
                var.set(&(var.as_tensor().detach() - update)?)?;
                Ok((m.detach(), v.detach()))
            };
            let (m, v) = run().map_err(ce)?;
            self.m[i] = m;
            self.v[i] = v;
        }
        Ok(())
    }
}
