"""The touchscreen page over HTTP (aiohttp), on a thread of its own, without ROS.

Routes: ``GET /`` the page, ``GET /static/<name>`` its assets (a fixed list, read from the
package: no CDN, no file path from the request), ``GET /events`` server-sent events (the
page's ``view()`` whenever it changes, and a comment every ``KEEPALIVE_S`` so a dead link
shows), ``GET /scene/<number>.png`` the picture of the question shown, ``POST /answer``,
``/skip`` and ``/next`` (JSON bodies of at most ``MAX_BODY`` bytes). Anything else, and every
refusal of ``FeedbackPage``, is answered with an HTTP error whose JSON says why, and reported
(``report(kind, message, where)``). With a token, every request but the assets' must carry it
(``?token=`` or the ``X-Page-Token`` header), the page's own address included.
"""
from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path
from typing import Callable

from aiohttp import web

from stars_ros.figures.scene import question_png
from stars_ros.hri.feedback_page import FeedbackPage, Refusal

ASSETS = Path(__file__).with_name('page')
FILES = {'page.css': 'text/css', 'page.js': 'text/javascript'}
MAX_BODY = 1024  # bytes: an answer is about 30
MAX_STREAMS = 16  # pages open at once (a robot has one screen; a few for tablets)
KEEPALIVE_S = 5.0
SECURITY_HEADERS = {'Content-Security-Policy': "default-src 'self'; img-src 'self'; frame-ancestors 'none'",
                    'X-Content-Type-Options': 'nosniff', 'Cache-Control': 'no-store'}
ERRORS = {400: 'bad_request', 404: 'not_found', 405: 'method', 413: 'oversized', 415: 'content_type',
          503: 'busy'}  # the kinds of aiohttp's and this module's HTTP errors; FeedbackPage's Refusal names its own


class PageServer:
    """Serves ``page`` (guarded by ``lock``) at ``host``:``port`` (0: a free port; ``address``
    says which once started). ``publish([(topic, payload)])`` sends what a tap gives;
    ``changed()`` (any thread) tells the open pages to look again."""

    def __init__(self, page: FeedbackPage, lock: threading.Lock, publish: Callable[[list], None],
                 report: Callable[[str, str, str], None], host: str, port: int):
        self.page, self.lock, self._publish, self._report = page, lock, publish, report
        self._host, self._port = host, port
        self.address = None
        self._loop = asyncio.new_event_loop()
        self._runner = None
        self._change = asyncio.Event()  # set at each change, then replaced (on the loop)
        self._streams = 0
        self._picture = (None, b'')  # (question number, PNG) of the last drawn
        self._drawing = threading.Lock()  # matplotlib draws one figure at a time
        self._index = (ASSETS / 'index.html').read_text(encoding='utf-8')
        self._files = {name: (ASSETS / name).read_bytes() for name in FILES}
        self._thread = threading.Thread(target=self._loop.run_forever, name='feedback-page-http', daemon=True)

    def start(self, timeout: float = 10.0) -> str:
        """Bind and serve; the address ``http://host:port/``. OSError when it cannot bind."""
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self._start(), self._loop).result(timeout)
        return self.address

    def stop(self, timeout: float = 5.0) -> None:
        if self._runner is not None:
            asyncio.run_coroutine_threadsafe(self._runner.cleanup(), self._loop).result(timeout)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout)

    def changed(self) -> None:
        self._loop.call_soon_threadsafe(self._wake)

    # -- inside the loop ----------------------------------------------------------------
    async def _start(self):
        app = web.Application(middlewares=[self._guard], client_max_size=MAX_BODY)
        app.add_routes([web.get('/', self._index_page), web.get('/static/{name}', self._static),
                        web.get('/favicon.ico', self._no_icon),
                        web.get('/events', self._events), web.get('/scene/{number:[0-9]{1,9}}.png', self._scene),
                        web.post('/answer', self._post), web.post('/skip', self._post),
                        web.post('/next', self._post)])
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=1.0)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self._host, self._port)
        await site.start()
        host, port = self._runner.addresses[0][:2]
        self.address = f'http://{"[" + host + "]" if ":" in host else host}:{port}/'

    def _wake(self):
        self._change.set()
        self._change = asyncio.Event()

    @web.middleware
    async def _guard(self, request: web.Request, handler):
        """The token first, then the handler; every refusal answered in JSON and reported."""
        try:
            if not request.path.startswith(('/static/', '/favicon.ico')):  # they hold nothing of anybody's
                with self.lock:
                    self.page.check_token(request.headers.get('X-Page-Token', request.query.get('token')))
            response = await handler(request)
        except Refusal as refusal:
            return self._refuse(request, refusal.kind, str(refusal), refusal.status)
        except web.HTTPException as error:
            if error.status < 400:
                raise
            limit = f' (a body may hold at most {MAX_BODY} bytes)' if error.status == 413 else ''
            return self._refuse(request, ERRORS.get(error.status, 'http'), error.reason + limit, error.status)
        response.headers.update(SECURITY_HEADERS)
        return response

    def _refuse(self, request: web.Request, kind: str, message: str, status: int) -> web.Response:
        where = f'http {request.method} {request.path[:100]}'
        self._report(kind, message, where)
        if request.method == 'GET' and request.path == '/':  # the page itself: a page that says why
            return web.Response(text=f'<!doctype html><html lang="en"><title>Refused</title><main><h1 role="alert">'
                                f'Refused: {kind}</h1><p>{_escape(message)}</p></main></html>', status=status,
                                content_type='text/html', headers=SECURITY_HEADERS)
        return web.json_response({'error': kind, 'message': message}, status=status, headers=SECURITY_HEADERS)

    async def _index_page(self, request):
        return web.Response(text=self._index, content_type='text/html')

    async def _no_icon(self, request):
        """The browser asks for it on its own: none, and no refusal to report."""
        return web.Response(status=204)

    async def _static(self, request):
        name = request.match_info['name']
        if name not in FILES:
            raise web.HTTPNotFound(reason=f'no asset {name[:64]!r}')
        return web.Response(body=self._files[name], content_type=FILES[name])

    async def _events(self, request):
        if self._streams >= MAX_STREAMS:
            raise web.HTTPServiceUnavailable(reason=f'{MAX_STREAMS} pages are open already')
        response = web.StreamResponse(headers={'Content-Type': 'text/event-stream', **SECURITY_HEADERS})
        self._streams += 1
        try:
            await response.prepare(request)
            shown = None
            while True:
                change = self._change
                with self.lock:
                    view = self.page.view()
                if view['version'] != shown:
                    await response.write(f'data: {json.dumps(view)}\n\n'.encode())
                    shown = view['version']
                try:
                    await asyncio.wait_for(change.wait(), KEEPALIVE_S)
                except asyncio.TimeoutError:
                    await response.write(b': still here\n\n')
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self._streams -= 1
        return response

    async def _scene(self, request):
        number = int(request.match_info['number'])
        with self.lock:
            scene = self.page.scene_of(number)
        if scene is None:  # a question no longer shown has no picture, drawn before or not
            raise web.HTTPNotFound(reason=f'no picture of question {number}: not shown now, or its scene was '
                                   'not seen on stars/scene')
        if self._picture[0] != number:
            self._picture = (number, await self._loop.run_in_executor(None, self._draw, *scene))
        return web.Response(body=self._picture[1], content_type='image/png')

    def _draw(self, scene, placement) -> bytes:
        with self._drawing:
            return question_png(scene, placement)

    async def _post(self, request):
        if request.content_type != 'application/json':
            raise web.HTTPUnsupportedMediaType(reason=f'expected application/json, got {request.content_type[:64]}')
        body = await request.read()  # client_max_size refuses a longer one (413)
        try:
            payload = json.loads(body) if body else {}
        except (ValueError, RecursionError) as error:  # UnicodeDecodeError is a ValueError
            raise web.HTTPBadRequest(reason=f'not JSON: {error}'[:200]) from None
        action = request.path.strip('/')
        with self.lock:
            out = (self.page.answer(payload) if action == 'answer' else self.page.skip(payload) if action == 'skip'
                   else self.page.next())
        self._publish(out)
        self._wake()
        sent = [topic for topic, _ in out if topic != 'stars/question_request']
        return web.json_response({'ok': True, 'sent': sent})


class ErrorThrottle:
    """At most one report per kind per ``period`` s, the refusals held back counted in the next."""

    def __init__(self, report: Callable[[str, str, str], None], period: float = 1.0,
                 clock: Callable[[], float] = time.monotonic):
        self._report, self._period, self._clock = report, period, clock
        self._last, self._held = {}, {}
        self._lock = threading.Lock()

    def __call__(self, kind: str, message: str, where: str) -> None:
        now = self._clock()
        with self._lock:
            if now - self._last.get(kind, -self._period) < self._period:
                self._held[kind] = self._held.get(kind, 0) + 1
                return
            self._last[kind] = now
            held = self._held.pop(kind, 0)
        self._report(kind, message + (f' ({held} more refused as {kind} before this one)' if held else ''), where)


def _escape(text: str) -> str:
    return text.replace('&', '&amp;').replace('<', '&lt;').replace('>', '&gt;')
