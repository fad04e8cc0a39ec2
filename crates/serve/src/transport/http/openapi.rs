//! The parts of the OpenAPI document that belong to no single route: its info, the bearer
//! security scheme every route but the operational ones requires, the tags, and the schemas
//! that only appear inside others (the SSE events' data).
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};

use crossview_api::types::{ErrorBody, FrameResult, FrameWithBoxes};

/// The document's tags.
pub(super) mod tags {
    /// Health, readiness, metrics and the document itself.
    pub const OPS: &str = "operations";
    /// The scenes: association, batches, results.
    pub const SCENES: &str = "scenes";
    /// Administration.
    pub const ADMIN: &str = "admin";
}

/// The document without its paths (the routes add theirs, see `routes::api_routes`).
#[derive(OpenApi)]
#[openapi(
    info(
        title = "crossview",
        description = "Associates people across several static cameras (Self-MVA). The HTTP \
            JSON API of `crossview serve`; the same port serves gRPC (`crossview.v1`, see \
            proto/). When the server has API keys, every route but `/healthz`, `/readyz`, \
            `/metrics` (and the live viewer's page at `/`) needs `Authorization: Bearer <key>`. \
            Every error answers `{\"error\": {\"kind\", \"message\", \"field\"}}`. \
            Regenerate docs/openapi.json with `crossview openapi > docs/openapi.json`.",
        license(name = "MIT OR Apache-2.0", identifier = "MIT OR Apache-2.0"),
    ),
    security(("bearer" = [])),
    modifiers(&BearerAuth),
    components(schemas(ErrorBody, FrameResult, FrameWithBoxes)),
    tags(
        (name = tags::OPS, description = "Health, readiness, metrics and this document"),
        (name = tags::SCENES, description = "Scenes: association, batches and results"),
        (name = tags::ADMIN, description = "Administration"),
    )
)]
pub(super) struct ApiDoc;

/// Adds the `bearer` security scheme (the server's `--api-key`s).
struct BearerAuth;

impl Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(
                HttpBuilder::new()
                    .scheme(HttpAuthScheme::Bearer)
                    .description(Some("One of the server's API keys (`--api-key`)"))
                    .build(),
            ),
        );
    }
}
