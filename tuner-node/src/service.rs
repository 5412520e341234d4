//! The `Tuner` gRPC service: the generator-nodes' `Attach` streams, status, decisions,
//! steering and previews.

use crate::check::check_summary;
use crate::engine::{Engine, Event};
use insitu_proto::pb;
use insitu_proto::pb::node_message::Msg as Up;
use insitu_proto::pb::tuner_message::Msg as Down;
use insitu_proto::pb::tuner_server::Tuner;
use std::pin::Pin;
use std::sync::Arc;
use tokio::sync::mpsc;
use tokio_stream::wrappers::{BroadcastStream, ReceiverStream};
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tracing::{warn, Instrument};

/// Decisions and refusals waiting for a node that reads slowly.
const NODE_BACKLOG: usize = 1024;

/// The gRPC service.
pub struct TunerService(pub Arc<Engine>);

type Boxed<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

#[tonic::async_trait]
impl Tuner for TunerService {
    type AttachStream = Boxed<pb::TunerMessage>;
    type WatchDecisionsStream = Boxed<pb::PmDecision>;

    #[tracing::instrument(
        name = "attach",
        skip_all,
        fields(peer = ?request.remote_addr(), node = tracing::field::Empty)
    )]
    async fn attach(
        &self,
        request: Request<Streaming<pb::NodeMessage>>,
    ) -> Result<Response<Self::AttachStream>, Status> {
        let mut inbound = request.into_inner();
        let hello = match inbound.message().await?.and_then(|m| m.msg) {
            Some(Up::Hello(h)) => h,
            _ => {
                return Err(Status::failed_precondition(
                    "the first message of an Attach stream must be a NodeHello",
                ))
            }
        };
        tracing::Span::current().record("node", hello.node_id.as_str());
        let (tx, rx) = mpsc::channel(NODE_BACKLOG);
        let e = self.0.clone();
        let conn = e.hub.connect(&hello.node_id, tx.clone());
        e.event(Event::Hello(conn, hello)).await;
        tokio::spawn(async move {
            let refuse = |message: String| {
                warn!(%message, "refused a message from a node");
                let _ = tx.try_send(Ok(pb::TunerMessage {
                    msg: Some(Down::Error(pb::TunerError { message })),
                }));
            };
            while let Ok(Some(m)) = inbound.message().await {
                match m.msg {
                    Some(Up::Summary(s)) => match check_summary(&s) {
                        Ok(()) => e.event(Event::Summary(conn, s)).await,
                        Err(problem) => refuse(problem),
                    },
                    Some(Up::Trial(r)) => {
                        if let Err(problem) = e.hub.trial_result(conn, r) {
                            refuse(problem);
                        }
                    }
                    Some(Up::Preview(f)) => {
                        if let Err(problem) = e.hub.preview_frame(conn, f) {
                            refuse(problem);
                        }
                    }
                    Some(Up::Ack(a)) if !a.error.is_empty() => {
                        warn!(pm_version = a.pm_version, error = %a.error, "a node refused a decision");
                    }
                    Some(Up::Ack(_)) => {}
                    Some(Up::Hello(_)) => refuse("a second NodeHello on one stream".into()),
                    None => refuse("an empty NodeMessage".into()),
                }
            }
            e.event(Event::Gone(conn)).await;
        }
        // The stream's reader logs under the stream's span (peer and node id).
        .in_current_span());
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn get_status(
        &self,
        _: Request<pb::StatusRequest>,
    ) -> Result<Response<pb::TunerStatus>, Status> {
        Ok(Response::new(self.0.status()))
    }

    async fn get_decision(
        &self,
        request: Request<pb::DecisionRequest>,
    ) -> Result<Response<pb::PmDecision>, Status> {
        let v = request.into_inner().pm_version;
        self.0.decision(v).map(Response::new).ok_or_else(|| {
            let latest = self.0.current().map_or(0, |d| d.pm_version);
            Status::not_found(format!(
                "no decision with version {v} (versions issued: {})",
                if latest == 0 {
                    "none yet".to_owned()
                } else {
                    format!("1..={latest}")
                }
            ))
        })
    }

    async fn watch_decisions(
        &self,
        _: Request<pb::StatusRequest>,
    ) -> Result<Response<Self::WatchDecisionsStream>, Status> {
        let rx = self.0.subscribe();
        let first = tokio_stream::iter(self.0.current().map(Ok));
        let rest = BroadcastStream::new(rx).filter_map(|r| r.ok().map(Ok));
        Ok(Response::new(Box::pin(first.chain(rest))))
    }

    async fn steer(
        &self,
        request: Request<pb::SteerRequest>,
    ) -> Result<Response<pb::SteerReply>, Status> {
        let mut req = request.into_inner();
        if req.who.is_empty() {
            req.who = "a gRPC client".into();
        }
        // Taken in order with the nodes' summaries by the engine's task.
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.0.event(Event::Steer(req, tx)).await;
        rx.await
            .map_err(|_| Status::unavailable("the tuner is stopping"))?
            .map(Response::new)
    }

    async fn preview(
        &self,
        request: Request<pb::PreviewRequest>,
    ) -> Result<Response<pb::PreviewReply>, Status> {
        crate::preview::preview(&self.0, request.into_inner())
            .await
            .map(Response::new)
    }
}
