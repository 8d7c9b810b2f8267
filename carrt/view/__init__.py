"""Watching the car from a browser: the live view of `carrt drive|teleop --view` and the episode
scrubber of `carrt episodes view`.

One small HTTP server (server.py, the standard library's ThreadingHTTPServer: nothing new to
install on a Jetson) serves a static page and the routes a feed gives it: live.py reads the
loop's LiveStatus, episodes.py reads recorded episodes. Everything a request costs (JSON, JPEG
with OpenCV) runs on the server's threads; the loop only swaps the LiveStatus reference it
already publishes every tick.
"""
