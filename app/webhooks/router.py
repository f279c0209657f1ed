"""Webhooks over HTTP: subscriptions, allowed targets, delivery log, test-fire."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, BackgroundTasks, Path, Query, Request, Response

from app.deps import AdminDep, ReadSessionDep, WriteSessionDep
from app.errors import error_responses
from app.events.service import LOGGED_TYPES
from app.webhooks import schemas, service

router = APIRouter(prefix="/v1", tags=["webhooks"])
WebhookId = Annotated[int, Path(ge=1, le=2**31 - 1)]


@router.get(
    "/webhooks/targets", response_model=schemas.WebhookTargets, responses=error_responses(401, 403)
)
def webhook_targets(s: ReadSessionDep, p: AdminDep) -> schemas.WebhookTargets:
    """The URL prefixes this operator's webhooks may deliver to (set by the service's
    administrator: `fleethealth webhooks allow`)."""
    return schemas.WebhookTargets(prefixes=service.targets(s, p.operator_id))


@router.post(
    "/webhooks",
    status_code=201,
    response_model=schemas.WebhookCreated,
    responses=error_responses(401, 403, 422),
)
def create_webhook(
    body: schemas.WebhookCreate, s: WriteSessionDep, p: AdminDep
) -> schemas.WebhookCreated:
    """Subscribe a URL to the operator's logged events (admin scope). The URL must be within
    the allowed targets (422 otherwise). The signing secret is returned here only."""
    row, secret = service.create_subscription(
        s,
        p.operator_id,
        body.url,
        body.event_types,
        body.tails,
        body.secret,
        body.description,
        LOGGED_TYPES,
    )
    return schemas.WebhookCreated(**service.subscription_public(row), secret=secret)


@router.get("/webhooks", response_model=schemas.WebhookList, responses=error_responses(401, 403))
def list_webhooks(s: ReadSessionDep, p: AdminDep) -> schemas.WebhookList:
    return schemas.WebhookList(
        items=[
            schemas.WebhookPublic(**service.subscription_public(r))
            for r in service.list_subscriptions(s, p.operator_id)
        ]
    )


@router.get(
    "/webhooks/{webhook_id:int}",
    response_model=schemas.WebhookPublic,
    responses=error_responses(401, 403, 404, 422),
)
def get_webhook(webhook_id: WebhookId, s: ReadSessionDep, p: AdminDep) -> schemas.WebhookPublic:
    return schemas.WebhookPublic(
        **service.subscription_public(service.get_subscription(s, p.operator_id, webhook_id))
    )


@router.delete(
    "/webhooks/{webhook_id:int}", status_code=204, responses=error_responses(401, 403, 404, 422)
)
def delete_webhook(webhook_id: WebhookId, s: WriteSessionDep, p: AdminDep) -> Response:
    """Remove a subscription, its pending deliveries and its delivery log."""
    service.delete_subscription(s, p.operator_id, webhook_id)
    return Response(status_code=204)


@router.post(
    "/webhooks/{webhook_id:int}/test",
    status_code=202,
    response_model=schemas.DeliveryPublic,
    responses=error_responses(401, 403, 404, 422),
)
def test_webhook(
    webhook_id: WebhookId, request: Request, tasks: BackgroundTasks, s: WriteSessionDep, p: AdminDep
) -> schemas.DeliveryPublic:
    """Queue a `webhook_test` delivery through the outbox (signed and retried like any
    other); follow it in the delivery log."""
    row = service.test_fire(s, p.operator_id, webhook_id)
    deliverer = getattr(request.app.state, "deliverer", None)
    if deliverer is not None:
        tasks.add_task(deliverer.wake)  # after the commit: the deliverer reads it from the database
    return schemas.DeliveryPublic.model_validate(service.delivery_public(row, []))


@router.get(
    "/webhooks/{webhook_id:int}/deliveries",
    response_model=schemas.DeliveryList,
    responses=error_responses(401, 403, 404, 422),
)
def webhook_deliveries(
    webhook_id: WebhookId,
    s: ReadSessionDep,
    p: AdminDep,
    status: schemas.DeliveryStatus | None = None,
    before: Annotated[
        int | None, Query(ge=1, le=2**53, description="Cursor: deliveries older than this id")
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> schemas.DeliveryList:
    """The delivery log, newest first: each delivery's status and every attempt."""
    return schemas.DeliveryList.model_validate(
        service.deliveries(s, p.operator_id, webhook_id, status, before, limit)
    )
