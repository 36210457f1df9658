// The robot's question to the person in front of it: the state comes from /events
// (server-sent events; the browser reconnects on its own), taps go to /answer, /skip, /next.
'use strict';
const token = new URLSearchParams(location.search).get('token');
const query = token ? '?token=' + encodeURIComponent(token) : '';
const WORDS = {2: ['bad', 'good'], 3: ['bad', 'neutral', 'good'], 5: ['very bad', 'bad', 'neutral', 'good', 'very good']};
const $ = (id) => document.getElementById(id);
// why the served person's answers are not kept (the view's not_kept)
const NOT_KEPT = {anonymous: 'The robot does not know who you are: your answer will not be kept.',
                  consent: 'You have not agreed to be remembered: your answer will not be kept.'};
const WHY_NOT_KEPT = {anonymous: 'the robot does not know who you are', consent: 'you have not agreed to be remembered'};
let shown = {phase: null, number: null};
let current = null;

function say(text) { $('refusal').textContent = text; }

async function post(path, body) {
  try {
    const response = await fetch(path + query, {method: 'POST', headers: {'Content-Type': 'application/json', ...(token ? {'X-Page-Token': token} : {})}, body: JSON.stringify(body)});
    const answer = await response.json();
    say(response.ok ? '' : 'Not taken: ' + answer.message);
  } catch (error) {
    say('Not sent: the robot cannot be reached. Please try again in a moment.');
  }
}

function ratingButtons(scale) {
  const box = $('rating');
  box.replaceChildren();
  const words = WORDS[scale.length] || [];
  scale.forEach((value, k) => {
    const button = document.createElement('button');
    button.type = 'button';
    button.textContent = words[k] ? words[k] : String(value);
    button.setAttribute('aria-label', (words[k] ? words[k] + ', ' : '') + 'rating ' + value);
    button.dataset.score = String(value);
    button.addEventListener('click', () => post('answer', {question: current.number, score: value}));
    box.appendChild(button);
  });
}

function show(view) {
  $('waiting').hidden = view.phase !== 'waiting';
  $('asking').hidden = view.phase !== 'question';
  $('thanks').hidden = view.phase !== 'thanks';
  $('waiting-title').textContent = !view.served ? 'The robot has no question for you right now.'
    : view.no_question ? 'The robot has not seen anything to ask you about yet: it will ask you once it has.'
    : 'Thinking of a question for you…';
  $('anonymous-note').hidden = !view.not_kept;
  $('anonymous-note').textContent = NOT_KEPT[view.not_kept] || '';
  current = view.question;
  if (view.phase === 'question' && current) {
    $('question-words').textContent = current.words;
    const picture = $('scene');
    picture.hidden = !current.has_picture;
    if (current.has_picture) {
      picture.src = 'scene/' + current.number + '.png' + query;
      picture.alt = 'The scene as the robot saw it, from above: the robot is the blue triangle, people are circles with an arrow for where they face' + (current.words.startsWith('move') ? ', and the star is where the robot would go.' : '.');
    }
    ratingButtons(view.scale);
  }
  $('kept-note').textContent = view.not_kept ? 'Your answer will not be kept: ' + WHY_NOT_KEPT[view.not_kept] + '.' : 'The robot will remember your answer.';
  const outcome = view.outcome;
  $('outcome').textContent = outcome ? 'The robot will now ' + outcome.words + '. It expects you to rate that ' + outcome.score.toFixed(2) + (outcome.score_sd != null ? ' ± ' + outcome.score_sd.toFixed(2) : '') + ' on the scale ' + view.scale[0] + ' to ' + view.scale[view.scale.length - 1] + '.' : 'The robot is working out what to do now…';
  $('next').textContent = view.pending ? 'Next question' : 'Ask me another question';
  const number = current ? current.number : null;
  if (view.phase !== shown.phase || number !== shown.number) {  // a new screen: focus its heading, so it is read out
    say('');
    const heading = {waiting: 'waiting-title', question: 'question-title', thanks: 'thanks-title'}[view.phase];
    $(heading).focus();
  }
  shown = {phase: view.phase, number: number};
  document.body.dataset.version = String(view.version);
}

function connect() {
  const events = new EventSource('events' + query);
  events.onopen = () => { $('connection').textContent = 'Connected to the robot.'; $('connection').classList.remove('lost'); };
  events.onmessage = (event) => show(JSON.parse(event.data));
  events.onerror = () => {
    $('connection').textContent = 'Connection to the robot lost: trying again…';
    $('connection').classList.add('lost');
    if (events.readyState === EventSource.CLOSED) {  // refused outright: try again later
      setTimeout(connect, 2000);
    }
  };
}

$('skip').addEventListener('click', () => post('skip', {question: current.number}));
$('next').addEventListener('click', () => post('next', {}));
connect();
