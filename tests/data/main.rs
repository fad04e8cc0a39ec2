//! The data layer: the recording format (SPEC §7), the WILDTRACK and MVOR importers and the split, and the
//! scene simulator, including the subcommands that drive them.

mod frame_rate;
mod mvor;
mod recording;
mod sim;
mod wildtrack;
