//! The live viewer: a web page at `/` that draws each camera's boxes of the scene's latest
//! frame, coloured by track id, from `GET /v1/scenes/{scene}/events?boxes=true`.
//!
//! The page, its script and its style sheet are plain files embedded in the binary
//! (`crates/serve/assets/`, no build step) and need no token: they hold no data. The page
//! asks for the API key when the server wants one (kept in the tab's `sessionStorage`) and
//! sends it as `Authorization: Bearer` on its API calls; it reads the event stream with
//! `fetch()` because `EventSource` cannot send headers, so the key never appears in a URL
//! or a log. Every asset goes out with a strict Content-Security-Policy (`default-src
//! 'self'`, no inline script or style, no external requests).
use axum::Router;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::routing::get;

const INDEX_HTML: &str = include_str!("../../../assets/index.html");
const VIEWER_JS: &str = include_str!("../../../assets/viewer.js");
const VIEWER_CSS: &str = include_str!("../../../assets/viewer.css");

/// The viewer's paths: `/` (the page), `/viewer.js`, `/viewer.css`.
pub const ASSETS: [&str; 3] = ["/", "/viewer.js", "/viewer.css"];

/// The Content-Security-Policy of every viewer asset: only this origin, no inline code, no
/// framing, no form submission (the token form is handled by the script).
pub const CONTENT_SECURITY_POLICY: &str = "default-src 'self'; base-uri 'none'; \
     form-action 'none'; frame-ancestors 'none'; object-src 'none'";

/// True for the viewer's asset paths (exempt from the API key, see [`crate::auth`]).
pub fn is_asset(path: &str) -> bool {
    ASSETS.contains(&path)
}

/// One asset with its content type and the security headers.
fn asset(content_type: &'static str, body: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CONTENT_SECURITY_POLICY, CONTENT_SECURITY_POLICY),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
            (header::X_FRAME_OPTIONS, "DENY"),
            (header::REFERRER_POLICY, "no-referrer"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        body,
    )
        .into_response()
}

async fn index() -> Response {
    asset("text/html; charset=utf-8", INDEX_HTML)
}

async fn script() -> Response {
    asset("text/javascript; charset=utf-8", VIEWER_JS)
}

async fn style() -> Response {
    asset("text/css; charset=utf-8", VIEWER_CSS)
}

/// The viewer's routes (merged into the HTTP router).
pub(crate) fn router<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new()
        .route(ASSETS[0], get(index))
        .route(ASSETS[1], get(script))
        .route(ASSETS[2], get(style))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_loads_only_its_own_assets() {
        assert!(INDEX_HTML.contains(r#"src="/viewer.js""#));
        assert!(INDEX_HTML.contains(r#"href="/viewer.css""#));
        // No inline script or style (the CSP forbids them) and nothing from elsewhere.
        assert!(!INDEX_HTML.contains("<script>"));
        assert!(!INDEX_HTML.contains("<style"));
        assert!(!INDEX_HTML.contains("style="));
        for text in [INDEX_HTML, VIEWER_JS, VIEWER_CSS] {
            assert!(!text.contains("http://") && !text.contains("https://"));
        }
        assert!(is_asset("/") && is_asset("/viewer.js") && !is_asset("/v1/scenes"));
    }
}
