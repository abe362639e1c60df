//! The OpenAPI 3.1 document of the HTTP API, served at `/openapi.json` (written by hand: the
//! API is small and mirrors proto/udapose/v1).

use serde_json::{Value, json};

pub fn document() -> Value {
    let error = json!({ "$ref": "#/components/schemas/Error" });
    let err = |description: &str| json!({ "description": description, "content": { "application/json": { "schema": error } } });
    let category = json!({ "name": "category", "in": "path", "required": true,
        "schema": { "type": "string", "pattern": "^[a-z0-9][a-z0-9_-]{0,63}$" } });
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
        "openapi": "3.1.0",
        "info": {
            "title": "udapose",
            "version": env!("CARGO_PKG_VERSION"),
            "description": "3D pose of objects from RGB images. Angles follow PASCAL3D+ (radians, with degree copies). The gRPC API (proto/udapose/v1) carries the same fields.",
        },
        "security": [{ "bearer": [] }],
        "paths": {
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
            "/healthz": { "get": { "summary": "Liveness", "security": [], "responses": { "200": { "description": "ok" } } } },
            "/readyz": { "get": { "summary": "Readiness: every model loaded", "security": [], "responses": { "200": { "description": "ready" }, "503": { "description": "not ready, with the reason" } } } },
            "/metrics": { "get": { "summary": "Prometheus metrics", "security": [], "responses": { "200": { "description": "text exposition format" } } } },
        },
        "components": {
            "securitySchemes": { "bearer": { "type": "http", "scheme": "bearer" } },
            "schemas": {
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
                "EstimateResponse": { "type": "object", "properties": {
                    "estimates": { "type": "array", "items": { "$ref": "#/components/schemas/PoseEstimate" } },
                    "model_version": { "type": "string" }, "frame_id": { "type": "string" },
                    "timings": { "$ref": "#/components/schemas/Timings" } } },
            },
        },
    })
}
