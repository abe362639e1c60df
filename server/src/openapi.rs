//! The OpenAPI 3.1 document of the HTTP API, served at `/openapi.json` (written by hand: the
//! API is small and mirrors proto/udapose/v1).

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
            "schemas": schemas(),
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
        "/v1/models": { "get": { "summary": "Every configured model", "responses": { "200": { "description": "{models: [{category, version, ready, error?}]}" } } } },
        "/v1/models/{category}": { "get": { "summary": "One model in detail", "parameters": [category],
            "responses": { "200": { "description": "category, version, generation, backbone, crop, cuboid, manifest" }, "404": err("Unknown category") } } },
        "/v1/models/{category}/versions": { "get": { "summary": "Every complete version and the activation log, newest first", "parameters": [category],
            "responses": { "200": { "description": "{versions: [{version, trained_as, active, job_id}], activations: [{generation, version, previous, actor, reason, time, job_id?}]}" }, "404": err("Unknown category") } } },
        "/v1/models/{category}/activate": { "post": { "summary": "Activate a version (admin)", "parameters": [category],
            "requestBody": { "required": true, "content": { "application/json": { "schema": { "type": "object", "required": ["version"],
                "properties": { "version": { "type": "string" }, "reason": { "type": "string" }, "expected_generation": { "type": "integer" } } } } } },
            "responses": { "200": { "description": "The new activation-log entry" }, "404": err("Unknown category or version"),
                "409": err("expected_generation is stale, or another activation won the race (ABORTED)") } } },
        "/v1/models/{category}/rollback": { "post": { "summary": "Re-activate the previous version (admin)", "parameters": [category],
            "requestBody": { "content": { "application/json": { "schema": { "type": "object",
                "properties": { "reason": { "type": "string" }, "expected_generation": { "type": "integer" } } } } } },
            "responses": { "200": { "description": "The new activation-log entry" }, "400": err("Nothing to roll back to (FAILED_PRECONDITION)"), "409": err("Stale expected_generation (ABORTED)") } } },
        "/v1/adapt/{category}/images": { "post": { "summary": "Buffer target-domain images for adaptation (write)", "parameters": [category],
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
        "/v1/jobs": { "get": { "summary": "Jobs, newest first", "parameters": [{ "name": "category", "in": "query", "schema": { "type": "string" } }],
            "responses": { "200": { "description": "{jobs: [Job]}" } } } },
        "/v1/jobs/{id}": { "get": { "summary": "One job", "parameters": [{ "name": "id", "in": "path", "required": true, "schema": { "type": "string" } }],
            "responses": { "200": { "description": "The job", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Job" } } } }, "404": err("No such job") } } },
        "/v1/jobs/{id}/events": { "get": { "summary": "The job's events as Server-Sent Events (event: job, id: seq), ending after the terminal one",
            "parameters": [{ "name": "id", "in": "path", "required": true, "schema": { "type": "string" } },
                           { "name": "after_seq", "in": "query", "description": "or the Last-Event-ID header", "schema": { "type": "integer" } }],
            "responses": { "200": { "description": "text/event-stream of JobEvent JSON" }, "404": err("No such job") } } },
        "/v1/jobs/{id}/cancel": { "post": { "summary": "Cancel a queued or running job (admin)",
            "parameters": [{ "name": "id", "in": "path", "required": true, "schema": { "type": "string" } }, { "name": "reason", "in": "query", "schema": { "type": "string" } }],
            "responses": { "200": { "description": "The job (CANCELLED once it stops)" }, "404": err("No such job") } } },
        "/healthz": { "get": { "summary": "Liveness", "security": [], "responses": { "200": { "description": "ok" } } } },
        "/readyz": { "get": { "summary": "Readiness: every model loaded", "security": [], "responses": { "200": { "description": "ready" }, "503": { "description": "not ready, with the reason" } } } },
        "/metrics": { "get": { "summary": "Prometheus metrics", "security": [], "responses": { "200": { "description": "text exposition format" } } } },
    })
}

/// The bodies' schemas.
fn schemas() -> Value {
    let number = json!({ "type": "number" });
    let angles = |extra: Value| {
        let mut props = json!({
            "azimuth": number, "elevation": number, "theta": number, "distance": number, "score": number,
        });
        if let (Some(p), Some(e)) = (props.as_object_mut(), extra.as_object()) {
            p.extend(e.clone());
        }
        props
    };
    json!({
        "Error": { "type": "object", "properties": { "error": { "type": "object", "properties": {
            "code": { "type": "string", "description": "gRPC code name, e.g. INVALID_ARGUMENT" }, "message": { "type": "string" } } } } },
        "Box": { "type": "object", "properties": { "x0": number, "y0": number, "x1": number, "y1": number } },
        "Hypothesis": { "type": "object", "properties": angles(json!({})) },
        "PoseEstimate": { "type": "object", "properties": angles(json!({
            "azimuth_deg": number, "elevation_deg": number, "theta_deg": number,
            "rotation": { "type": "array", "items": number, "description": "row-major R(a, e, theta)" },
            "hypotheses": { "type": "array", "items": { "$ref": "#/components/schemas/Hypothesis" } },
            "crop_box": { "$ref": "#/components/schemas/Box" },
            "cuboid": { "type": "array", "items": number, "description": "8 corners (x, y) in image pixels" },
            "model_version": { "type": "string" },
        })) },
        "Timings": { "type": "object", "properties": {
            "decode_ms": number, "queue_ms": number, "crop_ms": number, "backbone_ms": number,
            "solver_ms": number, "total_ms": number, "batch_size": { "type": "integer" } } },
        "JobEvent": { "type": "object", "properties": {
            "job_id": { "type": "string" }, "seq": { "type": "integer" }, "state": { "type": "string" }, "time": number,
            "message": { "type": "string" }, "round": { "type": "integer" }, "max_rounds": { "type": "integer" },
            "fired_ratio": number, "pose_change_median_deg": number, "images_used": { "type": "integer" },
            "images_held_out": { "type": "integer" }, "eta_seconds": number, "version": { "type": "string" },
            "gate": { "type": "array", "items": { "type": "object", "properties": {
                "name": { "type": "string" }, "active": number, "candidate": number, "threshold": number,
                "passed": { "type": "boolean" }, "detail": { "type": "string" } } } } } },
        "Job": { "type": "object", "properties": {
            "job_id": { "type": "string" }, "category": { "type": "string" },
            "state": { "type": "string", "enum": ["QUEUED", "RUNNING", "VALIDATING", "ACTIVATED", "REJECTED", "SUPERSEDED", "FAILED", "CANCELLED"] },
            "source_version": { "type": "string" }, "source_generation": { "type": "integer" }, "version": { "type": "string" },
            "created": number, "updated": number, "images_used": { "type": "integer" }, "images_held_out": { "type": "integer" },
            "reason": { "type": "string" }, "client_job_id": { "type": "string" },
            "last_event": { "$ref": "#/components/schemas/JobEvent" } } },
        "EstimateResponse": { "type": "object", "properties": {
            "estimates": { "type": "array", "items": { "$ref": "#/components/schemas/PoseEstimate" } },
            "model_version": { "type": "string" }, "frame_id": { "type": "string" },
            "timings": { "$ref": "#/components/schemas/Timings" } } },
    })
}
