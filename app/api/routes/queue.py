"""The operator's review and work queue: candidate verdicts, "no valid attitude", spacecraft, who writes."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Path
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.api.errors import ApiError
from app.api.routes.common import ID_LIMITS, get_context, operator_name, writer
from app.api.schemas import RejectRequest
from app.workflow import AppContext, confirm as confirming, queue, review as reviewing
from app.workflow.documents import OperatorDocument, RejectionDocument, ReviewDocument, SpacecraftDocument

router = APIRouter(prefix="/api", tags=["review"])
SeqId = Path(description="archive id of the sequence", **ID_LIMITS)
#: A bearer token read without requiring one: GET /api/operator answers with or without.
_optional_bearer = HTTPBearer(auto_error=False, description="The console's token, when the server needs one")


@router.get("/sequences/{seq_id}/review", response_model=ReviewDocument,
            summary="Each candidate's verdict (credible or not, and why), the sequence's verdict and audit trail")
def get_review(seq_id: int = SeqId, ctx: AppContext = Depends(get_context)):
    return reviewing.review(ctx, seq_id)


@router.post("/sequences/{seq_id}/reject", status_code=201, response_model=RejectionDocument,
             responses={200: {"description": "The sequence's verdict already is 'no valid attitude': that record"},
                        409: {"description": "The sequence has a confirmed attitude and supersede is false"}},
             summary="Record 'no valid attitude' for a sequence, with the reason, as its verdict")
def reject(body: RejectRequest, seq_id: int = SeqId, token_operator: str | None = Depends(writer),
           ctx: AppContext = Depends(get_context)):
    operator = operator_name(token_operator, body.operator)
    if operator is None:
        raise ApiError(422, "'no valid attitude' needs the operator's name",
                       problems=[{"location": "body.operator", "message": "missing operator"}])
    doc, created = confirming.reject(ctx, seq_id, operator, body.reason, supersede=body.supersede,
                                     replaces=None if body.replaces is None else body.replaces.key())
    return JSONResponse(doc.model_dump(mode="json"), status_code=201 if created else 200)


@router.get("/spacecraft", response_model=list[SpacecraftDocument],
            summary="Every spacecraft of the archive with its number of sequences")
def list_spacecraft(ctx: AppContext = Depends(get_context)):
    return queue.spacecraft_list(ctx)


@router.get("/operator", response_model=OperatorDocument,
            summary="Whether writes need a token here, and the operator of the token sent (if any)")
def get_operator(credentials: HTTPAuthorizationCredentials | None = Depends(_optional_bearer),
                 ctx: AppContext = Depends(get_context)):
    if credentials is None:
        return OperatorDocument(auth_required=ctx.access.require_token, operator=None)
    # A token that is sent must be valid, as for writes (writer() says so with a 401).
    return OperatorDocument(auth_required=ctx.access.require_token, operator=writer(credentials, ctx))
