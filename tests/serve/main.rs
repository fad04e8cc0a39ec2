//! The server's guarantees, one module per guarantee, each against the real server on
//! 127.0.0.1:0 with a real exported ONNX model and real clients (tonic, reqwest, curl, Python
//! grpcio). Fixtures: `crossview-testing`.

mod auth_and_origin;
mod bad_input;
mod camera_fit;
mod capture_times;
mod careless;
mod clock_offsets;
mod connections;
mod curl;
mod frame_cost;
mod frame_ids;
mod fuzz;
mod grpc_push_stream;
mod heal;
mod late_duplicate;
mod memory;
mod metrics_labels;
mod model_swap;
mod ndjson_bounds;
mod openapi;
mod openapi_fuzz;
mod overload;
mod partial;
mod record;
mod record_disk;
mod shutdown;
mod subscriber_budget;
mod sync_order;
mod tls;
mod tracking;
mod unary;
mod viewer;
