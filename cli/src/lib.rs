//! The `silvr` binary's library side: only the parts fuzzed on their own (fuzz/ links this crate). The
//! commands themselves live in the binary (`main.rs` and its modules).

pub mod http;
