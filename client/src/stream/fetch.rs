//! The fetch stage: network only. Each model's request goes out as one multi-range request (or
//! parallel singles, see [`crate::net::http`]), all models concurrently; the bodies come back
//! unchecked, beside their requests. Nothing is cached here: the residency stage checks and
//! keeps what arrived.

use bytes::Bytes;
use futures_util::future::join_all;

use super::model::Models;
use super::schedule::Request;
use crate::net::{NetError, RangeSource};

/// Fetches every request of the frame; one result per request, in the same order.
pub(crate) async fn fetch_all<S: RangeSource>(
    src: &S,
    models: &Models,
    requests: &[Request],
) -> Vec<Result<Vec<Bytes>, NetError>> {
    join_all(requests.iter().map(|r| src.fetch(models.url(r.model), &r.ranges))).await
}
