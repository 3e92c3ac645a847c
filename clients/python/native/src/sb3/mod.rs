//! The Stable-Baselines3 fast path of `tamrm.sb3.ShapedVecEnv`: one vector step shaped in
//! one native call ([`vecstep`]), the model's critic evaluated natively ([`mlp`]), and what
//! a shaped step records ([`record`]), shared with the wrapper's general path.

mod arrays;
pub(crate) mod mlp;
mod record;
pub(crate) mod vecstep;

pub(crate) use record::record_step;
