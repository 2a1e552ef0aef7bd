//! Protocol session (in progress).
