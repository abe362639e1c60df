//! The OpenAPI 3.1 document of the HTTP API, served at `/openapi.json`. The bodies' schemas are
//! derived from the types the handlers serialise (`udapose_api::schemas`); the routes, whose
//! multipart and raw-image bodies no derive describes well, are written here.

use serde_json::{Value, json};

pub fn document() -> Value {
    json!({
        "openapi": "3.1.0",
        "info": {
            "title": "udapose",
            "version": env!("CARGO_PKG_VERSION"),
            "description": "3D pose of objects from RGB images. Angles follow PASCAL3D+ (radians, with degree copies). The gRPC API (proto/udapose/v1) carries the same fields.",
        },
        "security": [{ "bearer": [] }],
        "paths": paths(),
        "components": {
            "securitySchemes": { "bearer": { "type": "http", "scheme": "bearer" } },
            "schemas": udapose_api::schemas(),
        },
    })
}

/// Every route, with its parameters and answers.
fn paths() -> Value {
    let number = json!({ "type": "number" });
    let error = json!({ "$ref": "#/components/schemas/Error" });
    let err = |description: &str| json!({ "description": description, "content": { "application/json": { "schema": error } } });
    let category = json!({ "name": "category", "in": "path", "required": true,
        "schema": { "type": "string", "pattern": "^[a-z0-9][a-z0-9_-]{0,63}$" } });
    json!({
        "/v1/pose/{category}": { "post": {
            "summary": "Estimate the pose of the object(s) in one image",
            "parameters": [
                category,
                { "name": "bbox", "in": "query", "style": "form", "explode": true, "description": "x0,y0,x1,y1 in image pixels; repeat for several objects; none: the image is the crop",
                  "schema": { "type": "array", "items": { "type": "string", "pattern": "^[^,]+,[^,]+,[^,]+,[^,]+$" } } },
                { "name": "width", "in": "query", "description": "raw RGB8 body: its width (with height)", "schema": { "type": "integer" } },
                { "name": "height", "in": "query", "schema": { "type": "integer" } },
                { "name": "frame_id", "in": "query", "schema": { "type": "string" } },
                { "name": "timeout_ms", "in": "query", "description": "give up if not started within this time", "schema": { "type": "integer" } },
            ],
            "requestBody": { "required": true, "content": {
                "image/png": { "schema": { "type": "string", "format": "binary" } },
                "image/jpeg": { "schema": { "type": "string", "format": "binary" } },
                "image/webp": { "schema": { "type": "string", "format": "binary" } },
                "application/octet-stream": { "schema": { "type": "string", "format": "binary" } },
                "multipart/form-data": { "schema": { "type": "object", "properties": { "image": { "type": "string", "format": "binary" } } } },
            } },
            "responses": {
                "200": { "description": "One estimate per box", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/EstimateResponse" } } } },
                "400": err("Bad image, box, query or category name"),
                "401": err("Missing or wrong token"),
                "403": err("The token lacks the role"),
                "404": err("Unknown category"),
                "413": err("Request body over the limit"),
                "503": { "description": "Overloaded or not ready; see Retry-After", "headers": { "Retry-After": { "schema": { "type": "integer" } } },
                         "content": { "application/json": { "schema": error } } },
                "504": err("The deadline passed before the estimate started"),
            },
        } },
        "/v1/models": { "get": { "summary": "Every configured model", "responses": { "200": { "description": "Every model", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Models" } } } } } } },
        "/v1/models/{category}": { "get": { "summary": "One model in detail", "parameters": [category],
            "responses": { "200": { "description": "The model", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/ModelDescription" } } } }, "404": err("Unknown category") } } },
        "/v1/models/{category}/versions": { "get": { "summary": "Every complete version and the activation log, newest first", "parameters": [category],
            "responses": { "200": { "description": "Versions and activation log", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Versions" } } } }, "404": err("Unknown category") } } },
        "/v1/models/{category}/activate": { "post": { "summary": "Activate a version (admin)", "parameters": [category],
            "requestBody": { "required": true, "content": { "application/json": { "schema": { "type": "object", "required": ["version"],
                "properties": { "version": { "type": "string" }, "reason": { "type": "string" }, "expected_generation": { "type": "integer" } } } } } },
            "responses": { "200": { "description": "The new activation-log entry", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Activation" } } } }, "404": err("Unknown category or version"),
                "409": err("expected_generation is stale, or another activation won the race (ABORTED)") } } },
        "/v1/models/{category}/rollback": { "post": { "summary": "Re-activate the previous version (admin)", "parameters": [category],
            "requestBody": { "content": { "application/json": { "schema": { "type": "object",
                "properties": { "reason": { "type": "string" }, "expected_generation": { "type": "integer" } } } } } },
            "responses": { "200": { "description": "The new activation-log entry", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Activation" } } } }, "400": err("Nothing to roll back to (FAILED_PRECONDITION)"), "409": err("Stale expected_generation (ABORTED)") } } },
        "/v1/adapt/{category}/images": { "post": { "summary": "Buffer target-domain images for adaptation, or with ?anchor=true keep them in the anchor set the gate guards (write)",
            "parameters": [category, { "name": "anchor", "in": "query", "schema": { "type": "boolean" } }],
            "requestBody": { "required": true, "content": {
                "image/png": { "schema": { "type": "string", "format": "binary" } },
                "multipart/form-data": { "schema": { "type": "object", "description": "one image per part" } } } },
            "responses": { "200": { "description": "{results: [{sha256, status: ACCEPTED|DUPLICATE|REJECTED, reason, buffered, capacity, job_id?}]}, one per image, once durable; Retry-After when any was BUFFER_FULL",
                "headers": { "Retry-After": { "schema": { "type": "integer" } } } }, "404": err("Unknown category"), "413": err("Request body over the limit") } } },
        "/v1/adapt/{category}/jobs": { "post": { "summary": "Start an adaptation job on the unclaimed buffered images, or return the running one (write)", "parameters": [category],
            "requestBody": { "content": { "application/json": { "schema": { "type": "object", "properties": {
                "overrides": { "type": "object", "properties": { "max_rounds": { "type": "integer" }, "learning_rate": number, "seed": { "type": "integer" } } },
                "client_job_id": { "type": "string", "description": "makes the call idempotent" } } } } } },
            "responses": { "200": { "description": "The job", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Job" } } } },
                "400": err("Too few buffered images (FAILED_PRECONDITION)"), "404": err("Unknown category") } } },
        "/v1/adapt/{category}/regression-sets": { "get": { "summary": "The regression sets the gate guards (held-out images of activated jobs, anchor images), oldest first", "parameters": [category],
            "responses": { "200": { "description": "The sets", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/RegressionSets" } } } }, "404": err("Unknown category") } } },
        "/v1/jobs": { "get": { "summary": "Jobs, newest first", "parameters": [{ "name": "category", "in": "query", "schema": { "type": "string" } }],
            "responses": { "200": { "description": "Jobs, newest first", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Jobs" } } } } } } },
        "/v1/jobs/{id}": { "get": { "summary": "One job", "parameters": [{ "name": "id", "in": "path", "required": true, "schema": { "type": "string" } }],
            "responses": { "200": { "description": "The job", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Job" } } } }, "404": err("No such job") } } },
        "/v1/jobs/{id}/events": { "get": { "summary": "The job's events as Server-Sent Events (event: job, id: seq), ending after the terminal one",
            "parameters": [{ "name": "id", "in": "path", "required": true, "schema": { "type": "string" } },
                           { "name": "after_seq", "in": "query", "description": "or the Last-Event-ID header", "schema": { "type": "integer" } }],
            "responses": { "200": { "description": "text/event-stream of JobEvent JSON" }, "404": err("No such job") } } },
        "/v1/jobs/{id}/cancel": { "post": { "summary": "Cancel a queued or running job (admin)",
            "parameters": [{ "name": "id", "in": "path", "required": true, "schema": { "type": "string" } }, { "name": "reason", "in": "query", "schema": { "type": "string" } }],
            "responses": { "200": { "description": "The job (CANCELLED once it stops)", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Job" } } } }, "404": err("No such job") } } },
        "/healthz": { "get": { "summary": "Liveness", "security": [], "responses": { "200": { "description": "ok" } } } },
        "/readyz": { "get": { "summary": "Readiness: every model loaded", "security": [], "responses": { "200": { "description": "ready" }, "503": { "description": "not ready, with the reason" } } } },
        "/metrics": { "get": { "summary": "Prometheus metrics", "security": [], "responses": { "200": { "description": "text exposition format" } } } },
    })
}
