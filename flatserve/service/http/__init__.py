"""The service's face: HTTP only, no math and no storage.

Routes (:mod:`.routes`, :mod:`.routes_lightfield`), their dependencies
(:mod:`.deps`), the lean path of the hot query endpoint (:mod:`.fastpath`), request
bodies in and response bodies out (:mod:`.codec`, :mod:`.responses`), errors as
responses (:mod:`.errors`), the middleware below the routes (:mod:`.guard`,
:mod:`.connections`, :mod:`.metrics`), the offline API docs (:mod:`.docs`) and the
viewer's static files. A route hands its work to a room
(:mod:`flatserve.service.rooms`), off the event loop when it is CPU-heavy.
"""
