//! The data layer: the recording format (SPEC §7), the WILDTRACK importers and split, and the
//! scene simulator, including the subcommands that drive them.

mod frame_rate;
mod recording;
mod sim;
mod wildtrack;
