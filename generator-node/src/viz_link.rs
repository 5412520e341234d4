//! A connection to the viz-node's `Viz` service, as every part of the node that calls it makes
//! one: shipping, the scene agreement, step outcomes and the exchange of faces.

use insitu_proto::auth::AttachToken;
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::peer::{error_chain, Peer};
use insitu_proto::transport;
use tonic::codegen::InterceptedService;
use tonic::transport::Channel;
use tonic::Status;

/// A client of the viz-node's `Viz` service, with the node's token.
pub(crate) type Client = VizClient<InterceptedService<Channel, AttachToken>>;

/// A client of the viz-node `peer`, messages up to the transport's limit.
///
/// # Errors
/// `UNAVAILABLE` naming the viz-node and why it could not be reached.
pub(crate) async fn connect(peer: &Peer) -> Result<Client, Status> {
    let channel = peer.connect().await.map_err(|e| {
        Status::unavailable(format!("viz-node {}: {}", peer.uri(), error_chain(&e)))
    })?;
    Ok(VizClient::with_interceptor(channel, peer.auth())
        .max_decoding_message_size(transport::MAX_MESSAGE_BYTES)
        .max_encoding_message_size(transport::MAX_MESSAGE_BYTES))
}
