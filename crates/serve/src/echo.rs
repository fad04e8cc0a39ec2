//! Bounded echoes of client input in error messages.
use std::borrow::Cow;

/// Longest error message (in bytes) sent back to a client: messages echo client input
/// (camera and scene names, JSON decoding errors), which must not come back unbounded.
pub(crate) const MAX_ERROR_MESSAGE: usize = 512;

/// `text` cut to at most [`MAX_ERROR_MESSAGE`] bytes (at a character boundary), saying how
/// long it was.
pub(crate) fn truncate_echo(text: &str) -> Cow<'_, str> {
    if text.len() <= MAX_ERROR_MESSAGE {
        return Cow::Borrowed(text);
    }
    let mut end = MAX_ERROR_MESSAGE;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    Cow::Owned(format!("{}… ({} bytes in all)", &text[..end], text.len()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn echoed_text_is_truncated_at_a_char_boundary() {
        assert_eq!(truncate_echo("short"), "short");
        let long = "é".repeat(1000);
        let t = truncate_echo(&long);
        assert!(t.len() < MAX_ERROR_MESSAGE + 40, "{}", t.len());
        assert!(t.ends_with("(2000 bytes in all)"), "{t}");
    }
}
